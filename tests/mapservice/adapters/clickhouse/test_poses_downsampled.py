"""poses_downsampled: one contract for MemoryStore and ClickHouseStore (embedded chDB).

The first pose per robot in each step [from + k*step, from + (k+1)*step) of the window,
ordered by time then robot, as both adapters must answer it.
"""

from __future__ import annotations

import time

import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import clone_migrated


@pytest.fixture
def t0() -> int:
    """A whole minute an hour ago (inside the retention)."""
    return (time.time_ns() // 1_000_000 // 60_000) * 60_000 - 3_600_000


def _key(rows, t0):
    return [(r.robot_id, r.ts_ms - t0) for r in rows]


def test_first_pose_per_robot_per_step(store, ev, t0) -> None:
    """Each robot keeps its first pose of each step; steps start at from_ms, not the epoch."""
    offsets = {"a": [0, 300, 999, 1000, 1700, 2500], "b": [50, 1050, 1100, 2999]}
    store.append([ev.pose(r, t0 + o, x=o / 1000) for r, os in offsets.items() for o in os])
    rows = store.poses_downsampled(t0, t0 + 3000, 1000)
    assert _key(rows, t0) == [
        ("a", 0),
        ("b", 50),
        ("a", 1000),
        ("b", 1050),
        ("a", 2500),
        ("b", 2999),
    ]
    assert [r.x for r in rows][:2] == [0.0, 0.05]
    # Shifting the window shifts the steps: [100, 1100), [1100, 2100), [2100, 3100).
    assert _key(store.poses_downsampled(t0 + 100, t0 + 3100, 1000), t0) == [
        ("a", 300),
        ("b", 1050),
        ("b", 1100),
        ("a", 1700),
        ("a", 2500),
        ("b", 2999),
    ]


def test_window_is_half_open_and_filters_robot(store, ev, t0) -> None:
    """from_ms <= t < to_ms; robot_id keeps one robot; limit keeps the earliest rows."""
    store.append([ev.pose(r, t0 + i * 500) for r in ("a", "b") for i in range(-2, 10)])
    rows = store.poses_downsampled(t0, t0 + 4000, 1000)
    assert _key(rows, t0) == [(r, s * 1000) for s in range(4) for r in ("a", "b")]
    assert _key(store.poses_downsampled(t0, t0 + 4000, 1000, robot_id="b"), t0) == [
        ("b", s * 1000) for s in range(4)
    ]
    assert store.poses_downsampled(t0, t0 + 4000, 1000, robot_id="nobody") == []
    assert len(store.poses_downsampled(t0, t0 + 4000, 1000, limit=3)) == 3
    assert _key(store.poses_downsampled(t0 + 1, t0 + 4000, 10_000), t0) == [("a", 500), ("b", 500)]


def test_step_of_one_ms_is_every_pose(store, ev, t0) -> None:
    """A step of 1 ms returns what poses() returns; a non-positive step is refused."""
    store.append([ev.pose(r, t0 + i * 7) for r in ("x", "y") for i in range(20)])
    assert store.poses_downsampled(t0, t0 + 1000, 1) == store.poses(t0, t0 + 1000)
    with pytest.raises(ValueError):
        store.poses_downsampled(t0, t0 + 1000, 0)


def test_redelivered_poses_count_once(store, ev, t0) -> None:
    """A re-delivered pose is one row, so a step still yields one pose per robot."""
    batch = [ev.pose("a", t0 + 10), ev.pose("a", t0 + 20)]
    store.append(batch)
    store.append(batch)
    assert _key(store.poses_downsampled(t0, t0 + 1000, 1000), t0) == [("a", 10)]


def test_adapters_agree_on_a_fleet(chdb_dir, ev, t0) -> None:
    """Both adapters return identical rows for a few robots over many steps."""
    events = [
        ev.pose(f"r{r}", t0 + 137 * i + r * 11, x=i * 0.001, battery_level=None if i % 3 else 50.0)
        for r in range(3)
        for i in range(200)
    ]
    memory = MemoryStore()
    ch = ClickHouseStore(f"chdb://{chdb_dir}", database="downsample_fleet")
    clone_migrated(chdb_dir, ch.database)
    try:
        for s in (memory, ch):
            s.migrate()
            s.append(events)
        for step in (500, 1000, 3333):
            assert ch.poses_downsampled(t0 + 50, t0 + 20_000, step) == memory.poses_downsampled(
                t0 + 50, t0 + 20_000, step
            )
        assert ch.poses_downsampled(
            t0, t0 + 30_000, 2000, robot_id="r1"
        ) == memory.poses_downsampled(t0, t0 + 30_000, 2000, robot_id="r1")
    finally:
        ch.close()
