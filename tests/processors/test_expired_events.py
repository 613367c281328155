"""Events older than the retention at the service's clock are not stored: records read
again from Kafka after the retention dropped their day (a group that lost its offsets
reads its topics from the start) must not bring that day back, nor the views, conflicts
and snapshots built over it."""

from __future__ import annotations

import asyncio

import pytest

from mapservice.core.events import encode
from mapservice.core.retention import DAY_MS
from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import EXPIRED, HistorySink
from mapservice.settings import Settings
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from tests.processors.history_consumer_kit import CHUNKS, NOW, POSES, drain, live_views

HOUR = 3_600_000


CONFLICT_GAP_MS = 20_000  # two robots' writes of one chunk this far apart: a conflict


def ages(retention_ms: int) -> tuple[list[int], list[int]]:
    """Ages (before NOW) the retention has forgotten, and ages it keeps: either side of
    the boundary by a millisecond, and far from it. A forgotten age leaves room for the
    conflicting write after it to be forgotten too."""
    gone = [retention_ms + CONFLICT_GAP_MS + 1, retention_ms + HOUR, 3 * retention_ms]
    kept = [retention_ms, retention_ms - 1, retention_ms // 2, HOUR, 0]
    return gone, kept


class Feed:
    def __init__(self) -> None:
        self.published: list = []

    def publish(self, events) -> None:
        self.published.extend(events)


def expired_count(topic: str) -> float:
    return EXPIRED.labels(topic)._value.get()


@pytest.mark.parametrize("retention_days", [1, 7, 24])
def test_a_batch_with_events_older_than_the_retention_stores_none_of_them(
    ev, retention_days: int
) -> None:
    """Poses of several robots and two robots' writes of each chunk 20 s apart (a
    conflict), at every forgotten age and every kept one, in one batch: only the kept
    ones are stored, pushed live and derived into the pose views, and only they record
    conflicts; every offset is committed (the records are not read again); each dropped
    event is counted per topic."""
    retention_ms = retention_days * DAY_MS
    gone, kept = ages(retention_ms)
    pose_ages = [retention_ms + 1, *gone, *kept]  # a pose a millisecond too old too
    source, store, feed = MemorySource(), MemoryStore(retention_days), Feed()
    sink = HistorySink(store, feed, retention_ms=retention_ms)
    views = live_views(
        Settings(conflict_window_s=60, retention_days=retention_days),
        store,
        None,
        sink.thread,
        now_ms=lambda: NOW,
    )
    views.load()
    for i, age in enumerate(pose_ages):
        source.append(POSES, encode(ev.pose(f"r{i % 3}", NOW - age)), partition=i % 2)
    for i, age in enumerate(gone + kept):
        t, gap = NOW - age, CONFLICT_GAP_MS
        source.append(CHUNKS, encode(ev.chunk("a", t, 1, i, bytes([i + 1]) * 10_000)))
        source.append(CHUNKS, encode(ev.chunk("b", t + gap, 1, i, bytes([i + 2]) * 10_000)))
    poses_before, chunks_before = expired_count(POSES), expired_count(CHUNKS)
    consumer = HistoryConsumer(
        source, sink, views, batch_size=1000, batch_seconds=0.01, now_ms=lambda: NOW
    )
    drain(consumer)
    asyncio.run(consumer.settle())

    stored_poses = {p.ts_ms for p in store.poses(0, NOW + 1, limit=10_000)}
    assert stored_poses == {NOW - age for age in kept}
    stored_chunks = {(c.robot_id, c.ts_ms) for c in store.chunk_events(0, NOW + DAY_MS)}
    assert stored_chunks == {("a", NOW - age) for age in kept} | {
        ("b", NOW - age + CONFLICT_GAP_MS) for age in kept
    }
    boundary = NOW - retention_ms
    assert all(e.event_time_ms >= boundary for e in feed.published)
    assert len(feed.published) == 3 * len(kept)  # a pose and two chunk writes each
    assert store.map_at(boundary - 1) == []  # no chunk state before the retention
    assert store.poses_downsampled(0, boundary, 1000) == []
    assert {c.ts_ms for c in store.conflicts(0, NOW + DAY_MS)} == {
        NOW - age + CONFLICT_GAP_MS for age in kept
    }
    assert expired_count(POSES) - poses_before == len(gone) + 1
    assert expired_count(CHUNKS) - chunks_before == 2 * len(gone)
    assert source.committed == {
        (POSES, 0): len(range(0, len(pose_ages), 2)),
        (POSES, 1): len(range(1, len(pose_ages), 2)),
        (CHUNKS, 0): 2 * len(gone + kept),
    }


def test_state_older_than_the_retention_is_stored(ev) -> None:
    """The map meta is state the retention keeps however old: read again (a new group
    reads the compacted meta topic from its start), it is stored."""
    source, store = MemorySource(), MemoryStore()
    old_meta = ev.meta(NOW - 30 * DAY_MS)
    source.append("meta", encode(old_meta))
    sink = HistorySink(store, retention_ms=7 * DAY_MS)
    drain(
        HistoryConsumer(source, sink, None, batch_size=10, batch_seconds=0.01, now_ms=lambda: NOW)
    )
    assert store.latest_meta() == old_meta.payload


def test_a_replayed_topic_is_logged_once_a_minute_not_per_event(ev, monkeypatch) -> None:
    """A topic read again from its start drops its events in every batch: one structured
    line says how many, per topic, at most once a minute of the sink's clock."""
    from mapservice.processors import sink as sink_module

    clock = {"t": 1000.0}
    sink = HistorySink(MemoryStore(), retention_ms=DAY_MS, monotonic=lambda: clock["t"])
    old = [ev.pose("r1", NOW - 2 * DAY_MS - i) for i in range(5)]
    lines: list[dict] = []

    class Log:
        def warning(self, message: str, **fields) -> None:
            lines.append(fields)

    monkeypatch.setattr(sink_module, "log", Log())
    for _batch in range(7):  # a batch every 20 s for two minutes
        assert sink.unexpired(POSES, old, NOW) == []
        clock["t"] += 20.0
    fresh = [ev.pose("r1", NOW)]
    assert sink.unexpired(POSES, fresh, NOW) == fresh
    assert [line["dropped"] for line in lines] == [{POSES: 5}, {POSES: 15}, {POSES: 15}]
    assert {line["boundary_ms"] for line in lines} == {NOW - DAY_MS}
