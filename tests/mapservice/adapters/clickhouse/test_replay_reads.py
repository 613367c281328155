"""The replay reads at plant scale: they use the snapshots and the per-minute
tables, and give what the naive queries over every event give, edge cases included."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import clone_migrated

_db = itertools.count()


@pytest.fixture
def store(chdb_dir):
    """An empty, migrated ClickHouseStore with 10-minute snapshots."""
    s = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"replay_{next(_db)}", snapshot_every_ms=600_000
    )
    clone_migrated(chdb_dir, s.database)
    s.migrate()
    yield s
    s.close()


@pytest.fixture
def h0() -> int:
    """A whole hour about two hours ago (inside the retention)."""
    return (time.time_ns() // 1_000_000 // 3_600_000 - 2) * 3_600_000


def test_reads_use_a_snapshot_when_no_repair_is_pending(store, ev, h0) -> None:
    """With no repair pending the newest snapshot at or before T is used: writes and poses
    older than it are read from the snapshot, not from the events (deleted here)."""
    store.append([ev.chunk("a", h0 + 1000, 0, 0), ev.pose("r", h0 + 2000, x=7.0)])
    assert store.build_snapshots(h0 + 600_000) > 0
    snapshots = store.client.query(
        f"SELECT toUnixTimestamp64Milli(snap_ts) FROM {store.database}.snapshot_log"
    ).result_rows
    assert max(ts for (ts,) in snapshots if ts <= h0 + 700_000) == h0 + 600_000
    # Events before the snapshot gone: only a read that uses the snapshot still sees the write.
    store.client.command(f"DELETE FROM {store.database}.chunk_events WHERE 1")
    (chunk,) = store.map_at(h0 + 700_000)
    assert (chunk.robot_id, chunk.ts_ms) == ("a", h0 + 1000)
    assert [(p.robot_id, p.ts_ms, p.x) for p in store.robots_at(h0 + 700_000)] == [
        ("r", h0 + 2000, 7.0)
    ]


# --- a history with the edge cases, in both stores -------------------------------------------


def _history(ev, h0: int) -> tuple[list, list]:
    """Events over 40 minutes from h0 (3 robots, chunk writes on second and bucket edges,
    two writes in one millisecond, a robot that goes silent), and a late batch: a pose
    and a write into the first snapshot interval, and a re-delivered write."""
    rng = np.random.default_rng(11)
    events = []
    for robot, period, until in (("a", 1000, 40), ("b", 2300, 40), ("quiet", 5000, 7)):
        for t in range(int(rng.integers(0, 999)), until * 60_000, period):
            events.append(ev.pose(robot, h0 + t, x=t / 1000))
    for t in sorted(
        {int(t) for t in rng.integers(0, 40 * 60_000, 400)}
        | {0, 999, 1000, 59_999, 60_000, 86_400, 86_399, 600_000, 1_234_567}
    ):
        events.append(ev.chunk("ab"[t % 2], h0 + t, t % 3, t % 4, bytes([t % 7]) * 10_000))
    events.append(ev.chunk("b", h0 + 1000, 0, 1))  # same millisecond, other robot and chunk
    late = [
        ev.pose("b", h0 + 301_500, x=-1.0),
        ev.chunk("quiet", h0 + 302_000, 2, 2),
        ev.chunk("ab"[600_000 % 2], h0 + 600_000, 0, 0, bytes([600_000 % 7]) * 10_000),
    ]
    return events, late


WINDOWS = [  # (from offset, to offset, buckets)
    (0, 40 * 60_000, 40),
    (0, 40 * 60_000, 4),
    (0, 30 * 60_000, 1000),  # whole minutes
    (12_345, 38 * 60_000 + 777, 25),  # off the minute: buckets of ~91 s
    (12_345, 38 * 60_000 + 777, 3),
    (1, 40 * 60_000, 2),  # over ten minutes, off the minute
    (60_000, 36 * 60_000, 1000),  # 2,160 ms buckets: every edge inside a second
    (1000, 35 * 60_000 + 1000, 33),  # whole seconds, buckets of 63.6 s
    (59_999, 62_001, 3),
    (250_000, 350_000, 50),  # short: buckets under a minute
    (-3_600_000, 3_600_000, 100),  # around the history
]


def _stores(chdb_dir, ev, h0):
    memory = MemoryStore()
    ch = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"replay_{next(_db)}", snapshot_every_ms=600_000
    )
    clone_migrated(chdb_dir, ch.database)
    ch.migrate()
    events, late = _history(ev, h0)
    for s in (memory, ch):
        for i in range(0, len(events), 97):
            s.append(events[i : i + 97])
    return memory, ch, late


def test_timeline_equals_the_fold_before_and_after_snapshots_and_repairs(chdb_dir, ev, h0) -> None:
    """The timeline equals MemoryStore's (every event) for whole-minute, off-minute and
    off-second buckets, short ones, windows past the newest snapshot, with a late pose, a
    late write and a re-delivered write pending repair, and once repaired."""
    memory, ch, late = _stores(chdb_dir, ev, h0)
    try:

        def check():
            for lo, hi, n in WINDOWS:
                assert ch.timeline(h0 + lo, h0 + hi, n) == memory.timeline(h0 + lo, h0 + hi, n), (
                    lo,
                    hi,
                    n,
                )

        check()  # no snapshot: every count from the events
        assert ch.build_snapshots(h0 + 30 * 60_000) > 0
        assert _count(ch, "chunk_seconds") > 0
        check()  # seconds before 30 min from chunk_seconds, the rest from the events
        for s in (memory, ch):
            s.append(late)
        assert _count(ch, "snapshot_repairs") == 1
        check()  # repair pending: chunk_seconds only before it
        while ch.repair_snapshots(max_snapshots=1):
            pass
        check()
    finally:
        ch.close()


def test_timeline_reads_chunk_seconds_and_pose_minutes(chdb_dir, ev, h0) -> None:
    """Covered seconds are counted from chunk_seconds and whole minutes' robots from
    pose_minutes: with those events deleted from chunk_events and poses, the timeline of
    buckets of a minute or more is unchanged."""
    memory, ch, _ = _stores(chdb_dir, ev, h0)
    try:
        ch.build_snapshots(h0 + 30 * 60_000)

        def read():  # chunk changes of every window, robots of those with buckets >= 1 min
            return [
                [
                    (b.chunk_changes, b.robots_active if (hi - lo) / n >= 60_000 else None)
                    for b in ch.timeline(h0 + lo, h0 + hi, n)
                ]
                for lo, hi, n in WINDOWS[:6]
            ]

        want = read()
        db = ch.database
        ch.client.command(
            f"DELETE FROM {db}.chunk_events WHERE ts < fromUnixTimestamp64Milli({h0 + 20 * 60_000})"
        )
        ch.client.command(
            f"DELETE FROM {db}.poses WHERE ts >= fromUnixTimestamp64Milli({h0 + 60_000}) "
            f"AND ts < fromUnixTimestamp64Milli({h0 + 35 * 60_000})"
        )
        assert (
            ch.chunk_events(h0, h0 + 20 * 60_000) == []
            and len(ch.poses(h0, h0 + 40 * 60_000)) < 1000
        )
        assert read() == want
        assert ch.timeline(h0, h0 + 40 * 60_000, 40) == memory.timeline(h0, h0 + 40 * 60_000, 40)
    finally:
        ch.close()


def test_robots_at_equals_the_fold(chdb_dir, ev, h0) -> None:
    """robots_at equals the fold of every pose at instants before, at and between
    snapshots, at minute edges, for a robot silent since long before T, with a late pose
    pending repair and once repaired."""
    memory, ch, late = _stores(chdb_dir, ev, h0)
    try:
        instants = [
            h0 - 1,
            h0 + 500,
            h0 + 600_000,
            h0 + 600_001,
            h0 + 1_260_000,
            h0 + 1_799_999,
            h0 + 2_400_000 + 59_999,
            h0 + 3_600_000,
            h0 + 301_600,
        ]
        ch.build_snapshots(h0 + 30 * 60_000)
        for s in (memory, ch):
            s.append(late)
        for repaired in (False, True):
            for at in instants:
                assert ch.robots_at(at) == memory.robots_at(at), (at - h0, repaired)
            while ch.repair_snapshots():
                pass
    finally:
        ch.close()


def test_whole_minute_downsampling_stops_at_the_limit_in_time_order(chdb_dir, ev, h0) -> None:
    """Keyframe reads in (cell, robot) order give the first pose per robot and step and
    the earliest `limit` of them, as the fold does, for steps of one and several minutes."""
    memory, ch, _ = _stores(chdb_dir, ev, h0)
    try:
        for f, t, step, limit in [
            (h0, h0 + 2_400_000, 60_000, 50),
            (h0 + 60_000, h0 + 2_000_000, 180_000, 7),
            (h0, h0 + 2_400_000, 600_000, 100_000),
        ]:
            assert ch.poses_downsampled(f, t, step, limit=limit) == memory.poses_downsampled(
                f, t, step, limit=limit
            )
            assert ch.poses_downsampled(
                f, t, step, robot_id="quiet", limit=limit
            ) == memory.poses_downsampled(f, t, step, robot_id="quiet", limit=limit)
    finally:
        ch.close()


def _count(store, table: str) -> int:
    return store.client.query(f"SELECT count() FROM {store.database}.{table}").result_rows[0][0]
