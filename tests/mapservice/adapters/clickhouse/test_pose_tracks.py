"""pose_tracks (schema v14): one robot's poses, sorted by robot, for its plots and track.

robot_track equals the memory fold (poses of that robot, downsampled or not, without
paths) with re-delivered, late and rewritten poses; v14 backfills an existing database and
later batches reach the table through derive_views; the retention drops it by day."""

from __future__ import annotations

import time

import msgspec
import numpy as np
import pytest

from mapservice.adapters.clickhouse.retention import RETAINED_BY_DAY
from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import pose_event


@pytest.fixture
def store(open_store):
    """A new database in the module's chDB (tests/conftest.py), not yet migrated."""
    s = open_store("clickhouse")
    yield s
    s.close()


TRACKS_VERSION = 17  # the migration that adds pose_tracks


def _m0() -> int:
    hour_ago = int(time.time() * 1000) - 3_600_000  # inside the retention
    return hour_ago - hour_ago % 60_000


def _without_paths(rows):
    return [msgspec.structs.replace(r, path=None) for r in rows]


def test_robot_track_equals_the_memory_fold_for_every_step(store) -> None:
    m0 = _m0()
    rng = np.random.default_rng(5)
    times = sorted({int(t) for t in rng.integers(0, 10 * 60_000, 400)} | {0, 59_999, 60_000})
    batches = [
        [
            pose_event(
                f"r{int(rng.integers(0, 3))}",
                m0 + t,
                x=float(i % 11),
                battery_level=float(i % 100),
                path=((1.0, 2.0), (3.0, 4.0)) if i % 5 == 0 else None,
            )
            for i, t in enumerate(times[k::3])
        ]
        for k in range(3)
    ]
    late = [pose_event("r1", m0 + times[1], x=-3.0), pose_event("r2", m0 + 125_000, x=9.5)]
    memory = MemoryStore()
    store.migrate()
    for s in (memory, store):
        for batch in [*batches, batches[0], late]:  # batches[0] re-delivered
            s.append(batch)
    for robot in ("r0", "r1", "r2", "nobody"):
        for f, t, step in [
            (m0, m0 + 600_000, 0),
            (m0 + 1_234, m0 + 333_333, 0),
            (m0, m0 + 600_000, 6_000),
            (m0 + 777, m0 + 600_000, 60_000),
            (m0, m0 + 600_000, 180_000),
            (m0 - 5, m0 + 599_999, 1_000),
        ]:
            want = memory.robot_track(robot, f, t, step)
            got = store.robot_track(robot, f, t, step)
            assert got == want, (robot, f, t, step)
            every = (
                memory.poses_downsampled(f, t, step, robot) if step else memory.poses(f, t, robot)
            )
            assert want == _without_paths(every)
    assert store.robot_track("r1", m0, m0 + 600_000, 0, limit=3) == memory.robot_track(
        "r1", m0, m0 + 600_000, 0, limit=3
    )
    assert any(p.x == -3.0 for p in store.robot_track("r1", m0, m0 + 600_000))
    with pytest.raises(ValueError):
        store.robot_track("r1", m0, m0 + 1, -1)


def test_v17_backfills_an_existing_database_then_follows_derive_views(store, monkeypatch) -> None:
    from mapservice.adapters.clickhouse import migrations as migrations_module

    released = migrations_module.migrations
    monkeypatch.setattr(
        migrations_module,
        "migrations",
        lambda db, days: [m for m in released(db, days) if m.version < TRACKS_VERSION],
    )
    assert store.migrate() == TRACKS_VERSION - 1
    m0 = _m0()
    store.append(
        [pose_event("r1", m0 + s * 1000, x=float(s)) for s in range(30)]
        + [pose_event("r2", m0 + 500, x=7.0)]
    )
    monkeypatch.setattr(migrations_module, "migrations", released)
    assert store.migrate() == SCHEMA_VERSION
    ((key,),) = store.client.query(
        "SELECT sorting_key FROM system.tables WHERE database = {d:String} AND name = 'pose_tracks'",
        parameters={"d": store.database},
    ).result_rows
    assert key == "robot_id, ts"
    assert [p.x for p in store.robot_track("r1", m0, m0 + 60_000)] == [float(s) for s in range(30)]
    later = [pose_event("r1", m0 + 40_000, x=40.0)]
    store.append_events(later)
    assert len(store.robot_track("r1", m0, m0 + 60_000)) == 30  # stored, not derived yet
    store.derive_views(later)
    store.derive_views(later)  # re-delivered: once
    assert [p.x for p in store.robot_track("r1", m0 + 35_000, m0 + 60_000)] == [40.0]
    store.client.command(f"DELETE FROM {store.database}.schema_migrations WHERE version = 14")
    assert store.migrate() == SCHEMA_VERSION  # a second run (re-backfill) changes nothing
    assert len(store.robot_track("r1", m0, m0 + 60_000)) == 31


def test_the_retention_drops_pose_tracks_by_day() -> None:
    assert "pose_tracks" in RETAINED_BY_DAY
