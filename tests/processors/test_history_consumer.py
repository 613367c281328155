"""The batch path from the event topics into the history: store first, then commit."""

from __future__ import annotations

import asyncio
import time

import pytest

from mapservice.core.events import encode
from mapservice.processors import history_consumer
from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import HistorySink
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from tests.processors.history_consumer_kit import (
    CHUNKS,
    NOW,
    POSES,
    FlakyStore,
    consumer_for,
    drain,
)


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
    source.commit = lambda records: (
        commits_seen_at_attempt.append(store.attempts),
        original_commit(records),
    )[1]
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
            self.batches.append(
                (
                    [e.event_time_ms for e in events],
                    {(e.robot_id, e.event_time_ms) for e in events} <= stored,
                    dict(source.committed),
                )
            )

    consumer = HistoryConsumer(
        source,
        HistorySink(store, Feed()),
        None,
        batch_size=100,
        batch_seconds=0.01,
        now_ms=lambda: NOW,
    )
    drain(consumer)
    # Stored when pushed, pushed before the offsets moved on.
    assert Feed.batches == [([NOW, NOW + 1, NOW + 2], True, {})] and store.attempts == 2


class FullDiskStore(MemoryStore):
    """Refuses every append as ClickHouse does on a full disk, until `full` is cleared."""

    def __init__(self) -> None:
        super().__init__()
        self.full = True
        self.attempts = 0

    def append_events(self, events) -> None:
        self.attempts += 1
        if self.full:
            raise RuntimeError(
                "Code: 243. DB::Exception: Cannot reserve 1.00 MiB, not enough "
                "space. (NOT_ENOUGH_SPACE)"
            )
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


class SlowStore(MemoryStore):
    """Each append takes `seconds`, as an insert into a loaded ClickHouse may."""

    def __init__(self, seconds: float) -> None:
        super().__init__()
        self.seconds = seconds

    def append_events(self, events) -> None:
        time.sleep(self.seconds)
        super().append_events(events)


@pytest.mark.parametrize(
    ("store", "stays"),
    [
        pytest.param(lambda: MemoryStore(), 0, id="quick-insert"),
        pytest.param(lambda: SlowStore(0.5), 3, id="slow-insert"),
        pytest.param(lambda: FlakyStore(failures=2), 3, id="insert-retried"),
    ],
)
def test_the_member_stays_in_its_group_while_a_batch_takes_long(ev, monkeypatch, store, stays):
    """A batch whose store takes longer than the stay interval (a slow or failing insert,
    retried; a rebuild goes the same way) asks the source to keep the member in its group
    meanwhile, and polls nothing: Kafka would else drop the member after
    max.poll.interval.ms, and its rejoin would rebuild the views again. A quick one does
    not ask."""
    monkeypatch.setattr(history_consumer, "STAY_IN_GROUP_EVERY_S", 0.1)
    source, made = MemorySource(), store()
    for i in range(3):
        source.append(POSES, encode(ev.pose("r1", NOW + i * 1000)))
    drain(consumer_for(made, source))
    assert made.counts().poses == 3 and source.committed == {(POSES, 0): 3}
    if stays:
        assert source.stays >= stays
    else:
        assert source.stays == 0
