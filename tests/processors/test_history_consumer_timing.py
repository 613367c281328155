"""The history consumer's timing: how long each poll waits for a batch (the batch window,
shortened by the time spent storing and adapting to the store's speed), and the latency
from an event's time to its being stored, on the service's clock."""

from __future__ import annotations

import asyncio

import pytest

from mapservice.core.events import encode
from mapservice.processors.batch_window import FILL_EVENTS
from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import HistorySink
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from tests.processors.history_consumer_kit import NOW, POSES, Clock, drain


class TimedStore(MemoryStore):
    """Each append takes `seconds` of the given clock."""

    def __init__(self, clock: Clock, seconds: float) -> None:
        super().__init__()
        self.clock, self.seconds = clock, seconds

    def append_events(self, events) -> None:
        self.clock.t += self.seconds
        super().append_events(events)


def timeouts_asked(
    ev,
    store_seconds: float,
    batches: int = 4,
    min_batch_seconds: float | None = None,
    idle_polls: int = 0,
    per_batch: int = FILL_EVENTS,
    quiet_batch_seconds: float | None = None,
) -> list[float]:
    """The poll timeouts of a consumer whose window is at most 200 ms (at least
    `min_batch_seconds`; None: always 200 ms), over `batches` stores of `per_batch` events
    each (by default a full batch: batch_window.FILL_EVENTS) and then `idle_polls` polls
    that find nothing."""
    clock = Clock()
    source, store = MemorySource(), TimedStore(clock, store_seconds)
    asked: list[float] = []
    original_poll = source.poll

    def poll(n, timeout_s):
        asked.append(round(timeout_s, 6))
        clock.t += timeout_s  # a poll with nothing to return early waits out its timeout
        return original_poll(per_batch, timeout_s)

    source.poll = poll
    for i in range(batches * per_batch):
        source.append(POSES, encode(ev.pose("r1", NOW + i * 1000)))
    consumer = HistoryConsumer(
        source,
        HistorySink(store),
        None,
        batch_size=max(100, per_batch),
        batch_seconds=0.2,
        min_batch_seconds=min_batch_seconds,
        quiet_batch_seconds=quiet_batch_seconds,
        now_ms=lambda: NOW,
        monotonic=clock,
    )

    async def go() -> None:
        for _ in range(batches + idle_polls):
            await consumer.run_once()

    asyncio.run(go())
    return asked


def test_time_spent_storing_counts_toward_the_next_batch_wait(ev) -> None:
    """After a 50 ms insert the next poll waits the remaining 150 ms of its 200 ms period."""
    assert timeouts_asked(ev, store_seconds=0.05) == [0.0, 0.15, 0.15, 0.15]


def test_after_an_insert_longer_than_the_period_the_next_poll_does_not_wait(ev) -> None:
    """A 300 ms insert is followed at once by the records queued meanwhile, not by another wait."""
    assert timeouts_asked(ev, store_seconds=0.3) == [0.0, 0.0, 0.0, 0.0]


def test_stored_events_record_their_end_to_end_latency_and_batch_size(ev) -> None:
    """Each stored event adds one observation from its event time and one from its receive time, per topic."""
    from prometheus_client import REGISTRY

    from mapservice.adapters.clock import SystemClock

    def count(name: str, topic: str) -> float:
        return REGISTRY.get_sample_value(f"{name}_count", {"topic": topic}) or 0.0

    before = (
        count("mapservice_event_to_stored_seconds", "lat-poses"),
        count("mapservice_received_to_stored_seconds", "lat-poses"),
    )
    batches_before = REGISTRY.get_sample_value("mapservice_sink_batch_events_count") or 0.0
    source, store = MemorySource(), MemoryStore()
    now = SystemClock().now_ms()
    for i in range(5):
        source.append("lat-poses", encode(ev.pose("r1", now - 3_000 + i)))
    drain(
        HistoryConsumer(
            source,
            HistorySink(store),
            None,
            batch_size=100,
            batch_seconds=0.01,
            now_ms=SystemClock().now_ms,
        )
    )
    assert count("mapservice_event_to_stored_seconds", "lat-poses") == before[0] + 5
    assert count("mapservice_received_to_stored_seconds", "lat-poses") == before[1] + 5
    assert (
        REGISTRY.get_sample_value("mapservice_sink_batch_events_count") or 0.0
    ) == batches_before + 1
    # Three seconds old when stored: in the (2, 5] s bucket of the event-time histogram.
    le2 = REGISTRY.get_sample_value(
        "mapservice_event_to_stored_seconds_bucket", {"topic": "lat-poses", "le": "2.0"}
    )
    le5 = REGISTRY.get_sample_value(
        "mapservice_event_to_stored_seconds_bucket", {"topic": "lat-poses", "le": "5.0"}
    )
    assert le5 - le2 == 5


def test_stored_latency_is_measured_on_the_service_clock(ev) -> None:
    """On a simulated clock (events stamped by it, the wall clock 30 days later) an event
    stored 3 s after its time counts 3 s, not 30 days."""
    from prometheus_client import REGISTRY

    def bucket(le: str) -> float:
        return (
            REGISTRY.get_sample_value(
                "mapservice_event_to_stored_seconds_bucket", {"topic": "sim-poses", "le": le}
            )
            or 0.0
        )

    before = bucket("5.0") - bucket("2.0")
    source, store = MemorySource(), MemoryStore()
    simulated_now = NOW - 30 * 86_400_000  # the wall clock is later still
    for i in range(4):
        source.append("sim-poses", encode(ev.pose("r1", simulated_now - 3_000 + i)))
    consumer = HistoryConsumer(
        source,
        HistorySink(store),
        None,
        batch_size=100,
        batch_seconds=0.01,
        now_ms=lambda: simulated_now,
    )
    drain(consumer)
    assert bucket("5.0") - bucket("2.0") == before + 4


def test_quick_stores_shorten_the_batch_window_to_its_shortest(ev) -> None:
    """With 10 ms stores the polls after the first wait 100 - 10 ms, not 200 - 10 ms."""
    assert timeouts_asked(ev, 0.01, batches=6, min_batch_seconds=0.1)[1:] == [0.09] * 5


def test_slow_stores_keep_the_longest_batch_window(ev) -> None:
    """With 90 ms stores (2.5 x 90 > 200 ms) every poll waits out the 200 ms window."""
    assert timeouts_asked(ev, 0.09, batches=6, min_batch_seconds=0.1)[1:] == [0.11] * 5


def test_an_idle_spell_shrinks_the_batch_window_back_to_its_shortest(ev) -> None:
    """After 90 ms stores (200 ms window) empty polls count as 0 s stores: 157, 110, then 100 ms
    (the batches' arrival rate fills a batch within the shortest window)."""
    asked = timeouts_asked(
        ev, 0.09, batches=6, min_batch_seconds=0.1, idle_polls=5, per_batch=2 * FILL_EVENTS
    )
    assert [round(t, 4) for t in asked[6:]] == [0.11, 0.1575, 0.1103, 0.1, 0.1]


@pytest.mark.parametrize("per_batch", [1, 2, 5, 10, 20])
def test_a_quiet_plant_gathers_its_events_for_the_longest_window(ev, per_batch) -> None:
    """Quick stores, but a few events per 100 ms (a plant of a few dozen robots): after the
    first batch shows the rate, every poll waits out the longest window (200 ms less the
    store), so the store's fixed cost is paid half as often."""
    asked = timeouts_asked(ev, 0.01, batches=6, min_batch_seconds=0.1, per_batch=per_batch)
    assert asked[2:] == [0.19] * 4


@pytest.mark.parametrize("per_batch", [1, 2, 5, 12, 20])
def test_a_quiet_plant_gathers_its_events_for_the_quiet_window(ev, per_batch) -> None:
    """With a quiet window of 500 ms (the default), a plant that brings fewer than
    FILL_EVENTS in it stores every 500 ms (less the store), once the running rate has
    settled on what the longer waits gather: a fifth of a second's batches were each a part
    of every table written and a merge of the day's partition started."""
    asked = timeouts_asked(
        ev, 0.01, batches=10, min_batch_seconds=0.1, per_batch=per_batch, quiet_batch_seconds=0.5
    )
    assert asked[1:] == sorted(asked[1:])  # lengthens as the rate settles, never beyond
    assert asked[-4:] == [0.49] * 4


@pytest.mark.parametrize("per_batch", [FILL_EVENTS, 2 * FILL_EVENTS, 5 * FILL_EVENTS])
@pytest.mark.parametrize("quiet_batch_seconds", [None, 0.5])
def test_a_busy_plant_keeps_the_shortest_window(ev, per_batch, quiet_batch_seconds) -> None:
    """Quick stores of full batches (1,000 robots and more): the shortest window, as
    before."""
    asked = timeouts_asked(
        ev,
        0.01,
        batches=6,
        min_batch_seconds=0.1,
        per_batch=per_batch,
        quiet_batch_seconds=quiet_batch_seconds,
    )
    assert asked[1:] == [0.09] * 5


def test_the_batch_window_gauge_reads_the_window_before_the_first_poll() -> None:
    """A new consumer exports its starting window (the longest), not 0."""
    from prometheus_client import REGISTRY

    HistoryConsumer(
        MemorySource(),
        HistorySink(MemoryStore()),
        None,
        batch_size=10,
        batch_seconds=0.25,
        min_batch_seconds=0.1,
    )
    assert REGISTRY.get_sample_value("mapservice_sink_batch_window_seconds") == 0.25
