"""The history consumer's derived views and conflicts: written once per interval for every
batch stored in it, always before the commit, and settled (or left uncommitted) on stop
and on a rebalance."""

from __future__ import annotations

import asyncio

from mapservice.core.events import encode
from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import HistorySink
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from tests.processors.history_consumer_kit import CHUNKS, NOW, POSES, Clock, drain, live_views


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
    drain(
        HistoryConsumer(
            source,
            HistorySink(OrderedStore(), Feed()),
            None,
            batch_size=100,
            batch_seconds=0.01,
            now_ms=lambda: NOW,
        )
    )
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
    consumer = HistoryConsumer(
        source,
        HistorySink(store),
        None,
        batch_size=batch_size,
        batch_seconds=0.2,
        now_ms=lambda: NOW,
        monotonic=clock,
        views_seconds=views_seconds,
    )

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
    consumer = HistoryConsumer(
        source,
        HistorySink(store),
        None,
        batch_size=100,
        batch_seconds=0.01,
        now_ms=lambda: NOW,
        views_seconds=60.0,
    )
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
    consumer = HistoryConsumer(
        source,
        HistorySink(AwayOnDerive()),
        None,
        batch_size=100,
        batch_seconds=0.01,
        now_ms=lambda: NOW,
        views_seconds=60.0,
    )
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
    assert (
        store.derived
        and REGISTRY.get_sample_value("mapservice_sink_derive_views_seconds_count") == before + 1
    )


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
    from mapservice.settings import Settings

    clock, source = Clock(), MemorySource()
    store = ConflictLog(source, failures)
    sink = HistorySink(store)
    views = live_views(Settings(conflict_window_s=60), store, None, sink.thread, now_ms=lambda: NOW)
    views.load()
    consumer = HistoryConsumer(
        source,
        sink,
        views,
        batch_size=100,
        batch_seconds=0.2,
        now_ms=lambda: NOW,
        monotonic=clock,
        views_seconds=views_seconds,
    )

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


def test_a_conflicts_incident_is_stored_before_its_batch_is_committed(ev) -> None:
    """Judged as the conflict is stored, not at the next batch or tick: a stop in between
    left a committed conflict unjudged, for good if the restart came more than the
    incidents' memory later."""
    _consumer, source, store, batch = conflicting_consumer(ev, views_seconds=0.0)
    batch(0, "a")
    batch(1, "b")
    assert store.conflict_writes and source.committed == {(CHUNKS, 0): 2}
    [incident] = [i for i in store.incidents(NOW - 60_000, NOW + 60_000) if i.kind == "conflict"]
    assert set(incident.robots) == {"a", "b"}
