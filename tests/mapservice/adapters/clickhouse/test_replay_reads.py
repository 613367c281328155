"""The replay reads at plant scale (issue 16): they use the snapshots and the per-minute
tables, and give what the naive queries over every event give, edge cases included."""

from __future__ import annotations

import itertools
import time

import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore

_db = itertools.count()


@pytest.fixture(scope="module")
def chdb_path(tmp_path_factory):
    """One chDB engine for the module, one database per test."""
    path = tmp_path_factory.mktemp("replay") / "ch"
    root = ClickHouseStore(f"chdb://{path}", database="replay_root")
    root.migrate()
    yield path
    root.close()


@pytest.fixture
def store(chdb_path):
    """An empty, migrated ClickHouseStore with 10-minute snapshots."""
    s = ClickHouseStore(f"chdb://{chdb_path}", database=f"replay_{next(_db)}",
                        snapshot_every_ms=600_000)
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
    assert store._snapshot_at_or_before(h0 + 700_000) == h0 + 600_000
    # Events before the snapshot gone: only a read that uses the snapshot still sees the write.
    store.client.command(f"DELETE FROM {store.database}.chunk_events WHERE 1")
    (chunk,) = store.map_at(h0 + 700_000)
    assert (chunk.robot_id, chunk.ts_ms) == ("a", h0 + 1000)
    assert [(p.robot_id, p.ts_ms, p.x) for p in store.robots_at(h0 + 700_000)] == [("r", h0 + 2000, 7.0)]
