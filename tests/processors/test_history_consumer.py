"""The batch path from the event topics into the history: store first, then commit."""

from __future__ import annotations

import asyncio

from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from mapservice.core.events import encode
from mapservice.processors.sink import HistorySink
from mapservice.processors.history_consumer import HistoryConsumer

NOW = 1_795_255_200_000
POSES, CHUNKS = "poses", "chunks"


class FlakyStore(MemoryStore):
    """Fails the first `failures` appends, as a ClickHouse that is briefly away would."""

    def __init__(self, failures: int) -> None:
        super().__init__()
        self.failures = failures
        self.attempts = 0

    def append_events(self, events) -> None:
        self.attempts += 1
        if self.failures:
            self.failures -= 1
            raise ConnectionError("clickhouse away")
        super().append_events(events)


def consumer_for(store: MemoryStore, source: MemorySource, batch: int = 100) -> HistoryConsumer:
    return HistoryConsumer(source, HistorySink(store), None, batch_size=batch, batch_seconds=0.01,
                           now_ms=lambda: NOW)


def drain(consumer: HistoryConsumer) -> None:
    async def go() -> None:
        await consumer.start()
        while await consumer.run_once():
            pass
    asyncio.run(go())


def test_every_record_is_stored_and_then_committed(ev) -> None:
    """Poses and chunks from several partitions all reach the store; every offset is committed."""
    source, store = MemorySource(), MemoryStore()
    for i in range(25):
        source.append(POSES, encode(ev.pose(f"r{i % 3}", NOW + i * 1000)), partition=i % 3)
    source.append(CHUNKS, encode(ev.chunk("r1", NOW, 1, 2)))
    drain(consumer_for(store, source, batch=7))
    assert store.counts().poses == 25 and store.counts().chunk_events == 1
    assert source.committed == {(POSES, 0): 9, (POSES, 1): 8, (POSES, 2): 8, (CHUNKS, 0): 1}


def test_a_failed_insert_is_retried_before_anything_is_committed(ev) -> None:
    """A store failure retries the same batch; the commit comes only after it was stored."""
    source, store = MemorySource(), FlakyStore(failures=2)
    source.append(POSES, encode(ev.pose("r1", NOW)))
    commits_seen_at_attempt = []
    original_commit = source.commit
    source.commit = lambda records: (commits_seen_at_attempt.append(store.attempts),
                                     original_commit(records))[1]
    drain(consumer_for(store, source))
    assert store.counts().poses == 1
    assert commits_seen_at_attempt == [3]


def test_undecodable_records_become_dead_letters_and_are_committed(ev) -> None:
    """Garbage on an event topic is stored as a dead letter; the good record beside it is stored."""
    source, store = MemorySource(), MemoryStore()
    source.append(POSES, b"\xc1 not an envelope")
    source.append(POSES, encode(ev.pose("r1", NOW)))
    drain(consumer_for(store, source))
    assert store.counts().dead_letters == 1 and store.counts().poses == 1
    assert source.committed == {(POSES, 0): 2}


def test_a_restart_before_the_commit_redelivers_without_duplicates(ev) -> None:
    """Records stored but not committed come again after a restart and are stored once."""
    source, store = MemorySource(), MemoryStore()
    for i in range(10):
        source.append(POSES, encode(ev.pose("r1", NOW + i * 1000)))
    source.fail_commits = True  # the consumer dies between insert and commit
    drain(consumer_for(store, source))
    source.fail_commits = False
    source.restart()
    drain(consumer_for(store, source))
    assert store.counts().poses == 10
    assert source.committed == {(POSES, 0): 10}


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class TimedStore(MemoryStore):
    """Each append takes `seconds` of the given clock."""

    def __init__(self, clock: Clock, seconds: float) -> None:
        super().__init__()
        self.clock, self.seconds = clock, seconds

    def append_events(self, events) -> None:
        self.clock.t += self.seconds
        super().append_events(events)


def timeouts_asked(ev, store_seconds: float, batches: int = 4,
                   min_batch_seconds: float | None = None, idle_polls: int = 0) -> list[float]:
    """The poll timeouts of a consumer whose window is at most 200 ms (at least
    `min_batch_seconds`; None: always 200 ms), over `batches` stores and then `idle_polls`
    polls that find nothing."""
    clock = Clock()
    source, store = MemorySource(), TimedStore(clock, store_seconds)
    asked: list[float] = []
    original_poll = source.poll

    def poll(n, timeout_s):
        asked.append(round(timeout_s, 6))
        clock.t += timeout_s  # a poll with nothing to return early waits out its timeout
        return original_poll(1, timeout_s)

    source.poll = poll
    for i in range(batches):
        source.append(POSES, encode(ev.pose("r1", NOW + i * 1000)))
    consumer = HistoryConsumer(source, HistorySink(store), None, batch_size=100, batch_seconds=0.2,
                               min_batch_seconds=min_batch_seconds, now_ms=lambda: NOW, monotonic=clock)

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


class CountingStore(MemoryStore):
    def __init__(self) -> None:
        super().__init__()
        self.appends: list[set[str]] = []

    def append_events(self, events) -> None:
        self.appends.append({type(e.payload).__name__ for e in events})
        super().append_events(events)


def test_a_batch_of_poses_and_chunks_is_stored_in_one_append_and_counted_per_topic(ev) -> None:
    """Poses and chunks polled together go to the store in a single append; the stored-events
    metric still counts each topic's events under its own label."""
    from prometheus_client import REGISTRY

    def stored(topic: str) -> float:
        return REGISTRY.get_sample_value("mapservice_sink_events_total", {"topic": topic}) or 0.0

    before = stored(POSES), stored(CHUNKS)
    source, store = MemorySource(), CountingStore()
    for i in range(3):
        source.append(POSES, encode(ev.pose("r1", NOW + i * 1000)))
    source.append(CHUNKS, encode(ev.chunk("r1", NOW, 1, 2)))
    drain(consumer_for(store, source))
    assert store.appends == [{"PoseReported", "ChunkUpdated"}]
    assert (stored(POSES) - before[0], stored(CHUNKS) - before[1]) == (3, 1)


def test_the_live_feed_gets_each_batch_once_it_is_queryable(ev) -> None:
    """The live feed is handed a batch only after its append returned (a failed one retried
    first), each event once, before the commit."""
    source, store = MemorySource(), FlakyStore(failures=1)
    for i in range(3):
        source.append(POSES, encode(ev.pose("r1", NOW + i)))

    class Feed:
        batches: list = []

        def publish(self, events) -> None:
            # Noted, not asserted here: the consumer would retry an exception raised here.
            stored = {(p.robot_id, p.ts_ms) for p in store.poses(0, 2 * NOW)}
            self.batches.append(([e.event_time_ms for e in events],
                                 {(e.robot_id, e.event_time_ms) for e in events} <= stored,
                                 dict(source.committed)))

    consumer = HistoryConsumer(source, HistorySink(store, Feed()), None, batch_size=100,
                               batch_seconds=0.01, now_ms=lambda: NOW)
    drain(consumer)
    # Stored when pushed, pushed before the offsets moved on.
    assert Feed.batches == [([NOW, NOW + 1, NOW + 2], True, {})] and store.attempts == 2


def test_stored_events_record_their_end_to_end_latency_and_batch_size(ev) -> None:
    """Each stored event adds one observation from its event time and one from its receive time, per topic."""
    from prometheus_client import REGISTRY

    from mapservice.adapters.clock import SystemClock

    def count(name: str, topic: str) -> float:
        return REGISTRY.get_sample_value(f"{name}_count", {"topic": topic}) or 0.0

    before = (count("mapservice_event_to_stored_seconds", "lat-poses"),
              count("mapservice_received_to_stored_seconds", "lat-poses"))
    batches_before = REGISTRY.get_sample_value("mapservice_sink_batch_events_count") or 0.0
    source, store = MemorySource(), MemoryStore()
    now = SystemClock().now_ms()
    for i in range(5):
        source.append("lat-poses", encode(ev.pose("r1", now - 3_000 + i)))
    drain(HistoryConsumer(source, HistorySink(store), None, batch_size=100, batch_seconds=0.01,
                          now_ms=SystemClock().now_ms))
    assert count("mapservice_event_to_stored_seconds", "lat-poses") == before[0] + 5
    assert count("mapservice_received_to_stored_seconds", "lat-poses") == before[1] + 5
    assert (REGISTRY.get_sample_value("mapservice_sink_batch_events_count") or 0.0) == batches_before + 1
    # Three seconds old when stored: in the (2, 5] s bucket of the event-time histogram.
    le2 = REGISTRY.get_sample_value("mapservice_event_to_stored_seconds_bucket", {"topic": "lat-poses", "le": "2.0"})
    le5 = REGISTRY.get_sample_value("mapservice_event_to_stored_seconds_bucket", {"topic": "lat-poses", "le": "5.0"})
    assert le5 - le2 == 5


def test_stored_latency_is_measured_on_the_service_clock(ev) -> None:
    """On a simulated clock (events stamped by it, the wall clock 30 days later) an event
    stored 3 s after its time counts 3 s, not 30 days."""
    from prometheus_client import REGISTRY

    def bucket(le: str) -> float:
        return REGISTRY.get_sample_value("mapservice_event_to_stored_seconds_bucket",
                                         {"topic": "sim-poses", "le": le}) or 0.0

    before = bucket("5.0") - bucket("2.0")
    source, store = MemorySource(), MemoryStore()
    simulated_now = NOW - 30 * 86_400_000  # the wall clock is later still
    for i in range(4):
        source.append("sim-poses", encode(ev.pose("r1", simulated_now - 3_000 + i)))
    consumer = HistoryConsumer(source, HistorySink(store), None, batch_size=100,
                               batch_seconds=0.01, now_ms=lambda: simulated_now)
    drain(consumer)
    assert bucket("5.0") - bucket("2.0") == before + 4


def test_quick_stores_shorten_the_batch_window_to_its_shortest(ev) -> None:
    """With 10 ms stores the polls after the first wait 100 - 10 ms, not 200 - 10 ms."""
    assert timeouts_asked(ev, 0.01, batches=6, min_batch_seconds=0.1)[1:] == [0.09] * 5


def test_slow_stores_keep_the_longest_batch_window(ev) -> None:
    """With 90 ms stores (2.5 x 90 > 200 ms) every poll waits out the 200 ms window."""
    assert timeouts_asked(ev, 0.09, batches=6, min_batch_seconds=0.1)[1:] == [0.11] * 5


def test_an_idle_spell_shrinks_the_batch_window_back_to_its_shortest(ev) -> None:
    """After 90 ms stores (200 ms window) empty polls count as 0 s stores: 157, 110, then 100 ms."""
    asked = timeouts_asked(ev, 0.09, batches=6, min_batch_seconds=0.1, idle_polls=5)
    assert [round(t, 4) for t in asked[6:]] == [0.11, 0.1575, 0.1103, 0.1, 0.1]


def test_the_batch_window_gauge_reads_the_window_before_the_first_poll() -> None:
    """A new consumer exports its starting window (the longest), not 0."""
    from prometheus_client import REGISTRY

    HistoryConsumer(MemorySource(), HistorySink(MemoryStore()), None, batch_size=10,
                    batch_seconds=0.25, min_batch_seconds=0.1)
    assert REGISTRY.get_sample_value("mapservice_sink_batch_window_seconds") == 0.25


def test_pose_views_are_derived_after_the_live_push_and_before_the_commit(ev) -> None:
    """append_events, push, derive_views (a failure retried), then commit: the views never delay the push."""
    calls: list[str] = []

    class OrderedStore(MemoryStore):
        derive_failures = 1

        def append_events(self, events) -> None:
            calls.append("append_events")
            super().append_events(events)

        def derive_views(self, events) -> None:
            calls.append("derive_views")
            if self.derive_failures:
                self.derive_failures -= 1
                raise ConnectionError("clickhouse away")

    class Feed:
        def publish(self, events) -> None:
            calls.append("publish")

    source = MemorySource()
    source.append(POSES, encode(ev.pose("r1", NOW)))
    original_commit = source.commit
    source.commit = lambda records: (calls.append("commit"), original_commit(records))[1]
    drain(HistoryConsumer(source, HistorySink(OrderedStore(), Feed()), None, batch_size=100,
                          batch_seconds=0.01, now_ms=lambda: NOW))
    assert calls == ["append_events", "publish", "derive_views", "derive_views", "commit"]


class DeriveLog(MemoryStore):
    """Notes each derive_views call's event times, and what was committed when it ran."""

    def __init__(self, source: MemorySource) -> None:
        super().__init__()
        self.source = source
        self.derived: list[tuple[list[int], dict]] = []

    def derive_views(self, events) -> None:
        self.derived.append(([e.event_time_ms for e in events], dict(self.source.committed)))


def deferring_consumer(ev, views_seconds: float, batch_size: int = 100):
    """A consumer on a hand-driven clock, its store noting derivations, and a way to add a
    one-pose batch that takes 0.3 s to poll and store."""
    clock, source = Clock(), MemorySource()
    store = DeriveLog(source)
    consumer = HistoryConsumer(source, HistorySink(store), None, batch_size=batch_size,
                               batch_seconds=0.2, now_ms=lambda: NOW, monotonic=clock,
                               views_seconds=views_seconds)

    def batch(i: int) -> int:
        source.append(POSES, encode(ev.pose("r1", NOW + i)))
        clock.t += 0.3
        return asyncio.run(consumer.run_once())
    return consumer, source, store, batch


def test_pose_views_are_derived_once_per_interval_for_every_batch_stored_in_it(ev) -> None:
    """With a 1 s interval and a batch every 0.3 s, one derive_views takes batches 0-4 and
    the commit waits for it: nothing is committed before."""
    _consumer, source, store, batch = deferring_consumer(ev, views_seconds=1.0)
    for i in range(4):  # the last 0.9 s after the first was stored
        batch(i)
        assert store.derived == [] and source.committed == {}
    batch(4)  # 1.2 s after
    assert store.derived == [([NOW, NOW + 1, NOW + 2, NOW + 3, NOW + 4], {})]
    assert source.committed == {(POSES, 0): 5}


def test_an_empty_poll_derives_and_commits_what_waits_at_once(ev) -> None:
    """Idle, nothing waits for the interval: the poll that finds nothing settles the batch before it."""
    consumer, source, store, batch = deferring_consumer(ev, views_seconds=60.0)
    batch(0)
    assert store.derived == [] and source.committed == {}
    assert asyncio.run(consumer.run_once()) == 0
    assert store.derived == [([NOW], {})] and source.committed == {(POSES, 0): 1}


def test_batch_size_events_waiting_are_derived_before_the_interval_ends(ev) -> None:
    """Memory is bounded: two batches of a batch_size of 2 settle without waiting for the interval."""
    _consumer, source, store, batch = deferring_consumer(ev, views_seconds=60.0, batch_size=2)
    batch(0)
    assert store.derived == []
    batch(1)
    assert store.derived == [([NOW, NOW + 1], {})] and source.committed == {(POSES, 0): 2}


def test_a_stopping_consumer_derives_and_commits_what_it_stored(ev) -> None:
    """Stop between intervals: the waiting batch is derived and committed before the source closes."""
    source, stopping = MemorySource(), asyncio.Event()
    store = DeriveLog(source)
    source.append(POSES, encode(ev.pose("r1", NOW)))
    consumer = HistoryConsumer(source, HistorySink(store), None, batch_size=100,
                               batch_seconds=0.01, now_ms=lambda: NOW, views_seconds=60.0)
    original_poll = source.poll

    def poll(n, timeout_s):
        stopping.set()  # the first poll is the last
        return original_poll(n, timeout_s)
    source.poll = poll
    asyncio.run(consumer.run(stopping))
    assert store.derived == [([NOW], {})] and source.committed == {(POSES, 0): 1}


def test_a_stop_with_the_store_away_gives_up_the_views_and_leaves_the_batch_uncommitted(ev) -> None:
    """One try on stop, no retry loop: the source closes, nothing is committed, and the batch comes again."""
    class AwayOnDerive(MemoryStore):
        def derive_views(self, events) -> None:
            raise ConnectionError("clickhouse away")

    source, stopping = MemorySource(), asyncio.Event()
    source.append(POSES, encode(ev.pose("r1", NOW)))
    consumer = HistoryConsumer(source, HistorySink(AwayOnDerive()), None, batch_size=100,
                               batch_seconds=0.01, now_ms=lambda: NOW, views_seconds=60.0)
    original_poll = source.poll

    def poll(n, timeout_s):
        stopping.set()
        return original_poll(n, timeout_s)
    source.poll = poll
    asyncio.run(asyncio.wait_for(consumer.run(stopping), 5))
    assert source.committed == {} and source.started is False


def test_a_rebalance_settles_what_was_stored_before_the_new_partitions_events(ev) -> None:
    """An assignment in a poll derives and commits the earlier batch before the poll's own records are stored."""
    consumer, source, store, batch = deferring_consumer(ev, views_seconds=60.0)
    batch(0)
    consumer.on_assigned([(POSES, 0)])
    batch(1)
    assert store.derived == [([NOW], {})] and source.committed == {(POSES, 0): 1}


def test_the_views_insert_is_timed(ev) -> None:
    """Each views insert is observed in mapservice_sink_derive_views_seconds."""
    from prometheus_client import REGISTRY

    before = REGISTRY.get_sample_value("mapservice_sink_derive_views_seconds_count") or 0
    _consumer, _source, store, batch = deferring_consumer(ev, views_seconds=1.0)
    for i in range(5):
        batch(i)
    assert store.derived and REGISTRY.get_sample_value("mapservice_sink_derive_views_seconds_count") == before + 1


class ConflictLog(DeriveLog):
    """DeriveLog that also notes each conflicts insert (with what was committed when it
    ran) and fails the first `failures` of them."""

    def __init__(self, source: MemorySource, failures: int = 0) -> None:
        super().__init__(source)
        self.failures = failures
        self.conflict_writes: list[tuple[list[str], dict]] = []

    def append_conflicts(self, rows) -> None:
        if self.failures:
            self.failures -= 1
            raise ConnectionError("clickhouse away")
        self.conflict_writes.append(([c.robot_b for c in rows], dict(self.source.committed)))
        super().append_conflicts(rows)


def conflicting_consumer(ev, views_seconds: float, failures: int = 0):
    """A consumer with live views (conflict window 60 s) on a hand-driven clock, and a way
    to add a one-chunk batch of a robot, each robot's pixels its own, taking 0.3 s."""
    from mapservice.processors.views import LiveViews
    from mapservice.settings import Settings

    clock, source = Clock(), MemorySource()
    store = ConflictLog(source, failures)
    sink = HistorySink(store)
    views = LiveViews(Settings(conflict_window_s=60), store, None, sink.thread, now_ms=lambda: NOW)
    views.load()
    consumer = HistoryConsumer(source, sink, views, batch_size=100,
                               batch_seconds=0.2, now_ms=lambda: NOW, monotonic=clock,
                               views_seconds=views_seconds)

    def batch(i: int, robot: str) -> int:
        source.append(CHUNKS, encode(ev.chunk(robot, NOW + i, 4, 4, bytes([ord(robot)]) * 10_000)))
        clock.t += 0.3
        return asyncio.run(consumer.run_once())
    return consumer, source, store, batch


def test_conflicts_are_written_once_per_interval_before_the_commit(ev) -> None:
    """Conflicts of batches 1-4 wait for the interval; one insert (a failure retried) takes them, then the commit."""
    _consumer, source, store, batch = conflicting_consumer(ev, views_seconds=1.0, failures=1)
    for i, robot in enumerate("abcde"):  # each after the first conflicts with the write before
        batch(i, robot)
        if i < 4:  # the fifth batch is stored 1.2 s after the first
            assert store.conflict_writes == [] and source.committed == {}
    assert store.conflict_writes == [(["b", "c", "d", "e"], {})]
    assert source.committed == {(CHUNKS, 0): 5}
    assert [c.robot_a for c in store.conflicts(NOW, NOW + 10)] == ["a", "b", "c", "d"]


def test_a_stopping_consumer_writes_the_conflicts_it_found(ev) -> None:
    """Stop between intervals: the conflicts found are stored and the batches committed."""
    consumer, source, store, batch = conflicting_consumer(ev, views_seconds=60.0)
    batch(0, "a")
    batch(1, "b")
    assert store.conflict_writes == []
    stopping = asyncio.Event()
    stopping.set()
    asyncio.run(consumer.run(stopping))
    assert store.conflict_writes == [(["b"], {})] and source.committed == {(CHUNKS, 0): 2}


def test_a_stop_with_the_conflicts_insert_failing_leaves_the_batches_uncommitted(ev) -> None:
    """One try on stop: a failing conflicts insert leaves nothing committed, so the batches come again."""
    consumer, source, store, batch = conflicting_consumer(ev, views_seconds=60.0, failures=1)
    batch(0, "a")
    batch(1, "b")
    stopping = asyncio.Event()
    stopping.set()
    asyncio.run(asyncio.wait_for(consumer.run(stopping), 5))
    assert store.conflict_writes == [] and source.committed == {} and source.started is False


class FullDiskStore(MemoryStore):
    """Refuses every append as ClickHouse does on a full disk, until `full` is cleared."""

    def __init__(self) -> None:
        super().__init__()
        self.full = True
        self.attempts = 0

    def append_events(self, events) -> None:
        self.attempts += 1
        if self.full:
            raise RuntimeError("Code: 243. DB::Exception: Cannot reserve 1.00 MiB, not enough "
                               "space. (NOT_ENOUGH_SPACE)")
        super().append_events(events)


def test_failing_inserts_are_reported_and_commit_nothing_until_they_succeed(ev) -> None:
    """While inserts fail: the sink's health is unready with the error, the failing gauge
    reads 1, and no offset is committed; once they succeed it recovers by itself, stores
    the batch once and commits it."""
    from prometheus_client import REGISTRY

    def gauge(name: str) -> float:
        return REGISTRY.get_sample_value(name)

    source, store = MemorySource(), FullDiskStore()
    for i in range(5):
        source.append(POSES, encode(ev.pose("r1", NOW + i * 1000)))
    consumer = consumer_for(store, source)
    health = consumer.sink.health

    async def go() -> None:
        await consumer.start()
        storing = asyncio.ensure_future(consumer.run_once())
        while store.attempts < 3:
            await asyncio.sleep(0.05)
        assert not health() and "NOT_ENOUGH_SPACE" in health.reason()
        assert gauge("mapservice_history_insert_failing") == 1.0
        assert gauge("mapservice_history_insert_failing_since_timestamp_seconds") > 0
        assert source.committed == {} and store.counts().poses == 0
        store.full = False
        assert await storing == 5
        await consumer.settle()

    asyncio.run(go())
    assert health() and health.reason() is None
    assert gauge("mapservice_history_insert_failing") == 0.0
    assert gauge("mapservice_history_insert_failing_since_timestamp_seconds") == 0.0
    assert gauge("mapservice_history_last_insert_timestamp_seconds") > 0
    assert store.counts().poses == 5 and source.committed == {(POSES, 0): 5}
