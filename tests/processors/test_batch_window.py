"""The history consumer's batch window: short while stores are quick, long once they slow."""

import pytest

from mapservice.processors.batch_window import FILL_EVENTS, STORE_SHARE, batch_window, smoothed


def test_a_quick_store_gets_the_shortest_window() -> None:
    """A 20 ms store would allow 50 ms; the window does not go below its shortest, 100 ms."""
    assert batch_window(0.02, 0.1, 0.2) == 0.1


def test_the_window_keeps_storing_at_its_share_of_the_loop() -> None:
    """A 60 ms store gets the window in which it takes STORE_SHARE of the time."""
    assert batch_window(0.06, 0.1, 0.2) == pytest.approx(0.06 / STORE_SHARE)
    assert 0.1 < batch_window(0.06, 0.1, 0.2) < 0.2


def test_a_slow_store_gets_the_longest_window() -> None:
    """Under load (a 150 ms store) the window is the longest, never more."""
    assert batch_window(0.15, 0.1, 0.2) == 0.2


def test_a_shortest_beyond_the_longest_is_the_longest() -> None:
    """A deployment that only lowered the longest window (0.01 s) gets exactly that."""
    assert batch_window(0.0, 0.1, 0.01) == 0.01


def test_after_one_slow_store_quick_ones_bring_the_shortest_window_back() -> None:
    """A 400 ms store after 30 ms ones moves the running time part of the way up, and ten
    quick stores later the window is the shortest again."""
    store = smoothed(0.03, 0.4)
    assert 0.03 < store < 0.4
    for _ in range(10):
        store = smoothed(store, 0.03)
    assert batch_window(store, 0.1, 0.2) == 0.1


def test_the_first_store_time_is_taken_as_it_is() -> None:
    """With nothing measured yet the first store time is the running time."""
    assert smoothed(None, 0.07) == 0.07


@pytest.mark.parametrize("events_per_s", [0.0, 1.0, 24.0, 120.0, 500.0, 999.0, 1200.0, 6000.0])
@pytest.mark.parametrize("store_s", [0.0, 0.01, 0.03, 0.06, 0.15])
def test_the_window_also_gathers_a_batch_worth_its_fixed_cost(store_s, events_per_s) -> None:
    """Whatever the store time, the window is long enough to gather FILL_EVENTS at the
    arrival rate, within the bounds: a quiet plant (none, or 24 events a second) stores
    every longest window, a plant of 1,000 robots and more keeps the store's own window."""
    window = batch_window(store_s, 0.1, 0.2, events_per_s)
    gather = FILL_EVENTS / events_per_s if events_per_s else float("inf")
    assert window == pytest.approx(min(0.2, max(0.1, store_s / STORE_SHARE, gather)))
    assert window >= batch_window(store_s, 0.1, 0.2)  # never shorter than the store's own
    if events_per_s >= FILL_EVENTS / 0.1:
        assert window == batch_window(store_s, 0.1, 0.2)


@pytest.mark.parametrize("quiet_s", [0.2, 0.5, 1.0])
@pytest.mark.parametrize("events_per_s", [0.0, 1.0, 24.0, 120.0, 480.0, 1200.0, 6000.0])
@pytest.mark.parametrize("store_s", [0.0, 0.01, 0.03, 0.06, 0.15, 0.4])
def test_a_quiet_plant_gathers_for_its_own_longer_window(store_s, events_per_s, quiet_s) -> None:
    """The gathering rule is bounded by the quiet window, the store's rule by the longest:
    24 events a second (20 robots) wait the whole quiet window, a plant that brings
    FILL_EVENTS within the shortest window keeps the store's own, and a slow store never
    waits beyond the longest unless the arrival rate is quiet."""
    window = batch_window(store_s, 0.1, 0.2, events_per_s, quiet_s)
    gather = FILL_EVENTS / events_per_s if events_per_s else float("inf")
    own = batch_window(store_s, 0.1, 0.2)
    assert own == pytest.approx(min(0.2, max(0.1, store_s / STORE_SHARE)))
    assert window == pytest.approx(max(own, min(quiet_s, max(0.1, gather))))
    assert own <= window <= max(0.2, quiet_s)
    if events_per_s >= FILL_EVENTS / 0.1:
        assert window == own
    if events_per_s <= FILL_EVENTS / quiet_s:
        assert window == pytest.approx(max(own, quiet_s))


def test_without_a_quiet_window_the_longest_bounds_the_gathering() -> None:
    """None (a consumer built without one) is the longest window, as before."""
    for rate in (0.0, 24.0, 300.0):
        assert batch_window(0.01, 0.1, 0.2, rate, None) == batch_window(0.01, 0.1, 0.2, rate, 0.2)
