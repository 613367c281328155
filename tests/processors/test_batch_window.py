"""The history consumer's batch window: short while stores are quick, long once they slow."""

import pytest

from mapservice.processors.batch_window import STORE_SHARE, batch_window, smoothed


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
