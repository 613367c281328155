"""The store contract, 2019 queries role (`LegacyQueries`, `StoreAdmin`'s deletes):
list_chunks, list_poses, delete_chunks, delete_meta.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py; shared helpers are in store_contract.py beside this module.
Times are taken from the wall clock (an hour ago, `t0`), because the ClickHouse tables drop
parts older than the retention.
"""

from __future__ import annotations

import pytest

from mapservice.core.legacy_query import parse_chunk_query, parse_pose_query
from mapservice.core.wire2019 import content_hash
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import clone_migrated, sparse_snapshots
from tests.mapservice.adapters.store_contract import clickhouse_store

# --- the 2019 REST contract: list_chunks, list_poses, delete_* ----------------------------


def _legacy_history(ev, t0):
    """Chunk writes and poses spread over two days, with ties in time, row and robot."""
    day = 86_400_000
    return [
        ev.chunk("r1", t0, 0, 0),
        ev.chunk("r2", t0, 0, 0),
        ev.chunk("r1", t0 + 1000, 0, 1),
        ev.chunk("r2", t0 + 2000, 1, 0, bytes([1]) * 10_000),
        ev.chunk("r1", t0 - 2 * 3_600_000, 1, 1),
        ev.chunk("r3", t0 - day - 5, 2, 0),
        ev.chunk("r1", t0 + 3000, 0, 0),
        ev.pose("r1", t0),
        ev.pose("r2", t0),
        ev.pose("r1", t0 + 1000),
        ev.pose("r2", t0 + 2000),
        ev.pose("r3", t0 - 2 * 3_600_000),
        ev.pose("r3", t0 - day - 5),
        ev.pose("r1", t0 + 3000),
    ]


def _chunk_keys(rows, t0):
    return [(r.ts_ms - t0, r.row, r.column, r.robot_id) for r in rows]


def test_list_chunks_default_is_newest_first_ten(store, ev, t0) -> None:
    """No parameters: the ten newest writes, newest first, ties by row, column, robot."""
    store.append(_legacy_history(ev, t0))
    rows = store.list_chunks(parse_chunk_query({}))
    assert _chunk_keys(rows, t0)[:5] == [
        (3000, 0, 0, "r1"),
        (2000, 1, 0, "r2"),
        (1000, 0, 1, "r1"),
        (0, 0, 0, "r1"),
        (0, 0, 0, "r2"),
    ]
    assert len(rows) == 7 and rows[0].content_hash == content_hash(bytes(10_000)).hex()


def test_list_chunks_filters(store, ev, t0) -> None:
    """row, column, robotId, timestamp, updatedSince (inclusive), updatedBefore (exclusive)."""
    store.append(_legacy_history(ev, t0))

    def keys(**params):
        return _chunk_keys(
            store.list_chunks(parse_chunk_query({k: str(v) for k, v in params.items()})), t0
        )

    assert keys(row=1) == [(2000, 1, 0, "r2"), (-7_200_000, 1, 1, "r1")]
    assert keys(column=1) == [(1000, 0, 1, "r1"), (-7_200_000, 1, 1, "r1")]
    assert keys(row=0, column=0, robotId="r2") == [(0, 0, 0, "r2")]
    assert keys(timestamp=t0) == [(0, 0, 0, "r1"), (0, 0, 0, "r2")]
    assert keys(updatedSince=t0 + 1000) == [
        (3000, 0, 0, "r1"),
        (2000, 1, 0, "r2"),
        (1000, 0, 1, "r1"),
    ]
    assert keys(updatedSince=t0, updatedBefore=t0 + 1000) == [(0, 0, 0, "r1"), (0, 0, 0, "r2")]


def test_list_chunks_sort_skip_limit(store, ev, t0) -> None:
    """sort orders by the whitelisted fields; skip and limit page through the result."""
    store.append(_legacy_history(ev, t0))

    def keys(**params):
        return _chunk_keys(store.list_chunks(parse_chunk_query(params)), t0)

    assert keys(sort="timestamp:asc", limit="2") == [
        (-86_400_005, 2, 0, "r3"),
        (-7_200_000, 1, 1, "r1"),
    ]
    assert keys(sort="row:desc,column:asc", limit="3") == [
        (-86_400_005, 2, 0, "r3"),
        (2000, 1, 0, "r2"),
        (-7_200_000, 1, 1, "r1"),
    ]
    assert keys(sort="robotId:desc", limit="1") == [(-86_400_005, 2, 0, "r3")]
    assert keys(skip="1", limit="2") == [(2000, 1, 0, "r2"), (1000, 0, 1, "r1")]
    assert keys(limit="0") == []


def test_list_poses_filters_sort_and_page(store, ev, t0) -> None:
    """robotId, timestamp, updatedSince/Before, sort, skip and limit on poses."""
    store.append(_legacy_history(ev, t0))

    def keys(**params):
        rows = store.list_poses(parse_pose_query({k: str(v) for k, v in params.items()}))
        return [(r.ts_ms - t0, r.robot_id) for r in rows]

    assert keys() == [
        (3000, "r1"),
        (2000, "r2"),
        (1000, "r1"),
        (0, "r1"),
        (0, "r2"),
        (-7_200_000, "r3"),
        (-86_400_005, "r3"),
    ]
    assert keys(robotId="r3") == [(-7_200_000, "r3"), (-86_400_005, "r3")]
    assert keys(timestamp=t0) == [(0, "r1"), (0, "r2")]
    assert keys(updatedSince=t0 + 1000, updatedBefore=t0 + 3000) == [(2000, "r2"), (1000, "r1")]
    assert keys(sort="robotId:desc,timestamp:asc", limit=3) == [
        (-86_400_005, "r3"),
        (-7_200_000, "r3"),
        (0, "r2"),
    ]
    assert keys(skip=5, limit=5) == [(-7_200_000, "r3"), (-86_400_005, "r3")]


@pytest.mark.parametrize(
    "params",
    [
        {},
        {"limit": "1"},
        {"limit": "3", "skip": "2"},
        {"sort": "timestamp:asc"},
        {"updatedBefore": "T+1500"},
        {"updatedBefore": "T+1500", "limit": "4"},
        {"sort": "column:desc,row:asc,timestamp:asc"},
        {"robotId": "r1", "sort": "row:asc"},
        {"limit": "10000"},
    ],
)
def test_adapters_agree_on_legacy_queries(chdb_dir, ev, t0, params) -> None:
    """ClickHouse answers every 2019 query exactly as the in-memory fold does."""
    params = {k: str(t0 + int(v[2:])) if v.startswith("T+") else v for k, v in params.items()}
    memory, clickhouse = MemoryStore(), clickhouse_store(chdb_dir)
    clone_migrated(chdb_dir, clickhouse.database)
    try:
        for s in (memory, clickhouse):
            s.migrate()
            s.append(_legacy_history(ev, t0))
        assert clickhouse.list_chunks(parse_chunk_query(params)) == memory.list_chunks(
            parse_chunk_query(params)
        )
        pose_params = {k: v for k, v in params.items() if "row" not in v and "column" not in v}
        assert clickhouse.list_poses(parse_pose_query(pose_params)) == memory.list_poses(
            parse_pose_query(pose_params)
        )
    finally:
        clickhouse.close()


def test_delete_chunks_empties_history_and_map(store, ev, t0) -> None:
    """delete_chunks removes every write, snapshot and conflict, keeps poses, counts what went."""
    from mapservice.core.ports import ConflictRow

    # Snapshots every 6 h: several of them over the history's day hold its chunks, not 145.
    sparse_snapshots(store)
    store.append(_legacy_history(ev, t0))
    store.append_conflicts([ConflictRow(0, 0, t0, "r2", t0, "r1")])
    assert len(store.conflicts(t0 - 1, t0 + 1)) == 1
    store.build_snapshots(t0 + 10_000)
    assert len(store.map_at(t0 + 10_000)) == 5
    assert store.delete_chunks() == 7
    assert store.list_chunks(parse_chunk_query({})) == []
    assert store.map_at(t0 + 10_000) == [] and store.chunk_events(t0 - 10**9, t0 + 10**6) == []
    assert store.counts().poses == 7 and store.conflicts(t0 - 1, t0 + 1) == []
    store.append([ev.chunk("r9", t0 + 5000, 4, 4)])  # writes after a delete are kept
    assert [(c.row, c.column) for c in store.map_at(t0 + 10_000)] == [(4, 4)]


def test_delete_meta_removes_every_meta(store, ev, t0) -> None:
    """delete_meta removes the stored metas: latest_meta is None until a new one is set."""
    store.append([ev.meta(t0), ev.meta(t0 + 1)])
    assert store.delete_meta() == 2
    assert store.latest_meta() is None
    store.append([ev.meta(t0 + 2, chunk_rows=7)])
    assert store.latest_meta().chunk_rows == 7
