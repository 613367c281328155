"""The store contract, time-travel role (`TimeTravelReader`, `SnapshotKeeper`): windows,
order and filters of poses and chunk writes, chunk contents, the timeline, keyframe
downsampling, late events against snapshots, robots at an instant page by page.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py; shared helpers are in store_contract.py beside this module.
Times are taken from the wall clock (an hour ago, `t0`), because the ClickHouse tables drop
parts older than the retention.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.core.ports import ChunkRow
from mapservice.core.wire2019 import content_hash
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import clone_migrated
from tests.mapservice.adapters.store_contract import clickhouse_store, random_pixels

# --- windows, order, filters -------------------------------------------------------------


def test_pose_window_is_half_open_and_ordered(store, ev, t0) -> None:
    """poses(from, to) holds from <= t < to, ordered by time then robot."""
    store.append(
        [
            ev.pose("r2", t0 + 1000),
            ev.pose("r1", t0 + 2000),
            ev.pose("r1", t0 + 1000),
            ev.pose("r3", t0),
            ev.pose("r1", t0 - 1),
        ]
    )
    rows = store.poses(t0, t0 + 2000)
    assert [(r.ts_ms - t0, r.robot_id) for r in rows] == [(0, "r3"), (1000, "r1"), (1000, "r2")]
    rows = store.poses(t0 + 1, t0 + 2001)
    assert [(r.ts_ms - t0, r.robot_id) for r in rows] == [(1000, "r1"), (1000, "r2"), (2000, "r1")]
    assert store.poses(t0 + 1, t0 + 1000) == []


def test_pose_robot_filter(store, ev, t0) -> None:
    """poses(..., robot_id) returns that robot's poses only."""
    store.append([ev.pose(r, t0 + i * 100) for i, r in enumerate(["a", "b", "a", "c", "a"])])
    rows = store.poses(t0, t0 + 10_000, robot_id="a")
    assert [r.ts_ms - t0 for r in rows] == [0, 200, 400]
    assert {r.robot_id for r in rows} == {"a"}
    assert store.poses(t0, t0 + 10_000, robot_id="nobody") == []


def test_pose_limit_keeps_the_earliest(store, ev, t0) -> None:
    """limit cuts the ordered result, keeping the earliest rows."""
    store.append([ev.pose("r1", t0 + i) for i in range(10, 0, -1)])
    assert [r.ts_ms - t0 for r in store.poses(t0, t0 + 100, limit=3)] == [1, 2, 3]


def test_chunk_event_window_is_half_open_and_ordered(store, ev, t0) -> None:
    """chunk_events(from, to) holds from <= t < to in event-time order (then row, column)."""
    store.append(
        [
            ev.chunk("r1", t0 + 500, 2, 0),
            ev.chunk("r1", t0, 1, 1),
            ev.chunk("r2", t0 + 500, 0, 3),
            ev.chunk("r1", t0 + 1000, 0, 0),
            ev.chunk("r1", t0 - 1, 0, 0),
        ]
    )
    rows = store.chunk_events(t0, t0 + 1000)
    assert [(r.ts_ms - t0, r.row, r.column, r.robot_id) for r in rows] == [
        (0, 1, 1, "r1"),
        (500, 0, 3, "r2"),
        (500, 2, 0, "r1"),
    ]
    assert [r.ts_ms - t0 for r in store.chunk_events(t0 + 1, t0 + 1001)] == [500, 500, 1000]
    assert len(store.chunk_events(t0, t0 + 1000, limit=1)) == 1


def test_chunk_row_fields(store, ev, t0) -> None:
    """A chunk row carries cell, robot, hex content hash and the receive time."""
    pixels = random_pixels(1)
    store.append([ev.chunk("r7", t0, 4, 5, pixels, receive_lag_ms=321)])
    assert store.chunk_events(t0, t0 + 1) == [
        ChunkRow(
            row=4,
            column=5,
            ts_ms=t0,
            robot_id="r7",
            content_hash=content_hash(pixels).hex(),
            receive_time_ms=t0 + 321,
        )
    ]


# --- chunk contents ----------------------------------------------------------------------


def test_chunk_content_returns_size_and_zlib_bytes(store, ev, t0) -> None:
    """chunk_content(hash) gives (width, height, the zlib bytes as sent); unknown is None."""
    pixels = random_pixels(2, 50 * 40)
    event = ev.chunk("r1", t0, 0, 0, pixels, width=50, height=40)
    store.append([event])
    found = store.chunk_content(content_hash(pixels))
    assert found is not None
    width, height, data = found
    assert (width, height) == (50, 40)
    assert isinstance(data, bytes) and data == event.payload.data
    assert zlib.decompress(data) == pixels
    assert store.chunk_content(bytes(16)) is None


def test_chunk_content_is_stored_once_per_hash(store, ev, t0) -> None:
    """Many writes of the same pixels store their content once; other pixels add one."""
    same = random_pixels(3)
    store.append([ev.chunk("r1", t0 + i, i % 3, i // 3, same) for i in range(6)])
    store.append([ev.chunk("r2", t0 + 10, 0, 0, same)])
    assert store.counts().chunk_contents == 1
    assert store.counts().chunk_events == 7
    assert {r.content_hash for r in store.chunk_events(t0, t0 + 100)} == {content_hash(same).hex()}
    store.append([ev.chunk("r2", t0 + 20, 0, 0, random_pixels(4))])
    assert store.counts().chunk_contents == 2


# --- time-travel replay reads: timeline, robot_known, keyframe downsampling --------------


@pytest.fixture
def m0(t0) -> int:
    """A whole minute about an hour ago (keyframes are per minute)."""
    return t0 // 60_000 * 60_000


def test_timeline_counts_chunks_conflicts_and_robots(store, ev, m0) -> None:
    """timeline() gives every bucket, empty ones too, for whole-minute and odd buckets alike."""
    from mapservice.core.ports import ConflictRow, TimelineBucket

    store.append(
        [
            ev.pose("r1", m0 + 1000),
            ev.pose("r2", m0 + 59_999),
            ev.pose("r1", m0 + 61_000),
            ev.pose("r3", m0 + 179_000),
            ev.pose("r3", m0 + 181_000),
            ev.chunk("r1", m0, 0, 0),
            ev.chunk("r2", m0 + 500, 0, 1),
            ev.chunk("r1", m0 + 125_000, 0, 0),
            ev.chunk("r1", m0 + 180_000, 0, 0),
        ]
    )
    store.append([ev.pose("r1", m0 + 1000)])  # a duplicate counts once
    store.append_conflicts([ConflictRow(0, 1, m0 + 500, "r1", m0, "r2")])
    assert store.timeline(m0, m0 + 180_000, 3) == [
        TimelineBucket(m0, 2, 1, 2),
        TimelineBucket(m0 + 60_000, 0, 0, 1),
        TimelineBucket(m0 + 120_000, 1, 0, 1),
    ]
    # 1,000 ms buckets starting off the minute: answered from every pose.
    assert store.timeline(m0 + 59_000, m0 + 62_000, 3) == [
        TimelineBucket(m0 + 59_000, 0, 0, 1),
        TimelineBucket(m0 + 60_000, 0, 0, 0),
        TimelineBucket(m0 + 61_000, 0, 0, 1),
    ]
    assert store.timeline(m0, m0, 5) == []


def test_append_events_then_derive_views_reads_as_append(store, ev, m0) -> None:
    """The history consumer's two steps (store, push, then derive) leave the store as one append does."""
    batch = [
        ev.pose("r1", m0 + 1000),
        ev.pose("r2", m0 + 61_000),
        ev.pose("r1", m0 + 125_000),
        ev.chunk("r1", m0 + 500, 0, 0),
    ]
    store.append_events(batch)
    assert store.poses(m0, m0 + 180_000) and store.chunk_events(m0, m0 + 180_000)  # queryable
    store.derive_views(batch)
    assert [(p.robot_id, p.ts_ms) for p in store.poses_downsampled(m0, m0 + 180_000, 60_000)] == [
        ("r1", m0 + 1000),
        ("r2", m0 + 61_000),
        ("r1", m0 + 125_000),
    ]
    assert [b.robots_active for b in store.timeline(m0, m0 + 180_000, 3)] == [1, 1, 1]


def test_robot_known(store, ev, t0) -> None:
    """robot_known() is true once a robot has a pose, false for one that never reported."""
    assert not store.robot_known("r1")
    store.append([ev.pose("r1", t0), ev.chunk("r2", t0)])
    assert store.robot_known("r1") and not store.robot_known("r2")


def test_whole_minute_downsampling_matches_every_pose(chdb_dir, ev, m0) -> None:
    """Downsampling from keyframes (whole-minute start and step, or steps of 10 min or more
    from any start) equals the memory fold, with late, out-of-order and rewritten poses and
    windows ending mid-minute."""
    rng = np.random.default_rng(3)
    times = sorted({int(t) for t in rng.integers(0, 10 * 60_000, 300)} | {12_345, 59_999, 60_000})
    batches = [
        [
            ev.pose(f"r{int(rng.integers(0, 3))}", m0 + t, x=float(i % 7))
            for i, t in enumerate(times[k::4])
        ]
        for k in range(4)
    ]
    # Late: an earlier pose of a minute that already has a keyframe; and a rewrite.
    late = [ev.pose("r0", m0 + 120_000, x=42.0), ev.pose("r1", m0 + times[0], x=-1.0)]
    memory, clickhouse = MemoryStore(), clickhouse_store(chdb_dir)
    clone_migrated(chdb_dir, clickhouse.database)
    try:
        for s in (memory, clickhouse):
            s.migrate()
            for batch in batches:
                s.append(batch)
            s.append(late)
        for f, t, step in [
            (m0, m0 + 600_000, 60_000),
            (m0, m0 + 600_000, 180_000),
            (m0 + 60_000, m0 + 290_500, 120_000),
            (m0, m0 + 600_000, 600_000),
            # off the minute, steps of >= 10 min: keyframes plus raw heads
            (m0 + 12_345, m0 + 600_000, 600_000),
            (m0 - 7, m0 + 599_000, 650_001),
            (m0 + 59_999, m0 + 600_000, 777_777),
        ]:
            want = memory.poses_downsampled(f, t, step)
            assert clickhouse.poses_downsampled(f, t, step) == want
            assert clickhouse.poses_downsampled(
                f, t, step, robot_id="r1"
            ) == memory.poses_downsampled(f, t, step, robot_id="r1")
        assert any(p.x == 42.0 for p in clickhouse.poses_downsampled(m0, m0 + 600_000, 60_000))
        assert clickhouse.timeline(m0, m0 + 600_000, 10) == memory.timeline(m0, m0 + 600_000, 10)
    finally:
        clickhouse.close()


def test_clickhouse_migration_v4_runs_twice_and_sorts_poses_by_time(chdb_dir, ev, t0) -> None:
    """Schema v4 re-sorts poses by (ts, robot_id) keeping every row; run again it changes
    nothing and the keyframe view still follows inserts."""
    store = clickhouse_store(chdb_dir)
    try:
        store.migrate()
        store.append([ev.pose("r1", t0), ev.pose("r2", t0 + 1)])
        db, c = store.database, store.client
        c.command(f"DELETE FROM {db}.schema_migrations WHERE version = 4")
        assert store.migrate() == SCHEMA_VERSION
        ((key,),) = c.query(
            "SELECT sorting_key FROM system.tables WHERE database = {d:String} AND name = 'poses'",
            parameters={"d": db},
        ).result_rows
        assert key == "ts, robot_id"
        store.append([ev.pose("r3", t0 + 2)])
        assert [p.robot_id for p in store.poses(t0, t0 + 10)] == ["r1", "r2", "r3"]
        assert all(store.robot_known(r) for r in ("r1", "r2", "r3"))
    finally:
        store.close()


def test_a_late_event_is_noted_not_rebuilt_and_reads_stay_exact(store, ev, t0) -> None:
    """A write 50 min late into 60 min of 10-min snapshots: append only notes the repair,
    reads are exact at once, and repair_snapshots rebuilds in bounded steps until done."""
    if isinstance(store, MemoryStore):
        assert store.repair_snapshots() == 0
        return
    store.snapshot_every_ms = 600_000
    base = t0 - 3_600_000
    store.append([ev.chunk("a", base + i * 60_000, 0, 0, bytes([i]) * 10_000) for i in range(61)])
    store.append([ev.pose("r", base + i * 60_000, x=float(i)) for i in range(61)])
    assert store.build_snapshots(base + 3_600_000) > 0
    snapshot_rows = store.client.query(
        f"SELECT count() FROM {store.database}.map_snapshots"
    ).result_rows[0][0]
    late = base + 10 * 60_000 + 30_000  # between snapshot 1 and 2, later than everything there
    store.append([ev.chunk("late", late, 0, 0, bytes([200]) * 10_000), ev.pose("r", late, x=99.0)])
    # Noted only: no snapshot row was written by the append.
    assert (
        store.client.query(f"SELECT count() FROM {store.database}.map_snapshots").result_rows[0][0]
        == snapshot_rows
    )
    at = base + 10 * 60_000 + 45_000
    (chunk,) = store.map_at(at)
    assert (chunk.robot_id, chunk.ts_ms) == ("late", late)
    assert store.robots_at(at)[0].x == 99.0
    before_next = base + 20 * 60_000 - 1  # the write at 19 min wins again after the late one
    assert store.map_at(before_next)[0].robot_id == "a"
    steps = []
    while (n := store.repair_snapshots(max_snapshots=2)) > 0:
        steps.append(n)
        assert len(steps) < 10
    assert steps and max(steps) <= 2
    assert (
        store.client.query(f"SELECT count() FROM {store.database}.snapshot_repairs").result_rows[0][
            0
        ]
        == 0
    )
    (chunk,) = store.map_at(at)  # now from a repaired snapshot: still the late write
    assert (chunk.robot_id, chunk.ts_ms) == ("late", late)
    assert store.robots_at(at)[0].x == 99.0


def test_robots_at_pages_in_robot_id_order_across_a_snapshot(store, ev, t0) -> None:
    """robots_at(after=, limit=) is a page of the whole answer, cut in the store (so a
    fleet of 100,000 ids is never read whole for /api/v1/robots): robots silent since a
    snapshot and robots that moved after it alike."""
    if hasattr(store, "snapshot_every_ms"):
        store.snapshot_every_ms = 600_000
    base = t0 - 3_600_000
    quiet = [f"q{i:02d}" for i in range(6)]  # only before the snapshot
    busy = [f"b{i:02d}" for i in range(5)]  # before and after it
    store.append([ev.pose(r, base + 1_000 + i) for i, r in enumerate(quiet + busy)])
    store.build_snapshots(base + 1_200_000)
    store.append([ev.pose(r, base + 1_500_000 + i, x=7.0) for i, r in enumerate(busy)])
    at = base + 1_800_000
    whole = store.robots_at(at)
    assert [p.robot_id for p in whole] == sorted(quiet + busy)
    pages, after = [], None
    while True:
        page = store.robots_at(at, after=after, limit=4)
        assert len(page) <= 4
        if not page:
            break
        pages.append(page)
        after = page[-1].robot_id
    assert [len(p) for p in pages] == [4, 4, 3]
    assert [(p.robot_id, p.ts_ms, p.x) for page in pages for p in page] == [
        (p.robot_id, p.ts_ms, p.x) for p in whole
    ]
    assert store.robots_at(at, after="b02", limit=2)[0].x == 7.0
    assert store.robots_at(at, after="zzz") == []
