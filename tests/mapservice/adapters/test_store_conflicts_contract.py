"""The store contract, conflict role (`ConflictReader`, and `append_conflicts`): the
conflicts' window, order and identity, their counts, the writes near chunks.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py; shared helpers are in store_contract.py beside this module.
Times are taken from the wall clock (an hour ago, `t0`), because the ClickHouse tables drop
parts older than the retention.
"""

from __future__ import annotations

from mapservice.core.ports import ConflictRow
from mapservice.core.wire2019 import content_hash

# --- conflicts ----------------------------------------------------------------------------


def _conflict(
    t0: int,
    dt: int,
    robot_a: str = "a",
    robot_b: str = "b",
    dt_a: int = 0,
    row: int = 1,
    column: int = 2,
):
    from mapservice.core.ports import ConflictRow

    return ConflictRow(row, column, t0 + dt, robot_a, t0 + dt_a, robot_b)


def test_conflicts_window_order_and_idempotence(store, t0) -> None:
    """conflicts(from, to) holds from <= ts < to in identity order; a repeat adds no row."""
    rows = [
        _conflict(t0, 2000, "c", "d"),
        _conflict(t0, 1000),
        _conflict(t0, 1000, row=0),
        _conflict(t0, 5000),
    ]
    store.append_conflicts(rows)
    store.append_conflicts(rows[:2])
    store.append_conflicts([])
    got = store.conflicts(t0, t0 + 5000)
    assert [(c.ts_ms - t0, c.row, c.robot_a) for c in got] == [
        (1000, 0, "a"),
        (1000, 1, "a"),
        (2000, 1, "c"),
    ]
    assert got[1] == rows[1]
    assert len(store.conflicts(t0, t0 + 6000, limit=2)) == 2


def test_conflict_identity_keeps_the_later_a(store, t0) -> None:
    """Two rows with one identity (B's) keep the one naming the later A, whatever the
    insert order; a row for another B of the same instant and chunk stays apart."""
    later = _conflict(t0, 1000, robot_a="c", dt_a=900)
    store.append_conflicts([later])
    store.append_conflicts([_conflict(t0, 1000, dt_a=500)])
    other_b = _conflict(t0, 1000, robot_b="e", dt_a=100)
    store.append_conflicts([other_b])
    assert store.conflicts(t0, t0 + 2000) == [later, other_b]


def test_conflict_counts_per_bucket(store, t0) -> None:
    """conflict_counts counts each identity once per bucket, keyed by the bucket start."""
    store.append_conflicts([_conflict(t0, 0), _conflict(t0, 999, row=3), _conflict(t0, 2500)])
    store.append_conflicts([_conflict(t0, 0)])
    assert store.conflict_counts(t0, t0 + 3000, 1000) == {t0: 2, t0 + 2000: 1}
    assert store.conflict_counts(t0 + 1, t0 + 3000, 1000) == {t0 + 1: 1, t0 + 2001: 1}


def test_chunk_writes_near_filters_chunks_and_closed_window(store, ev, t0) -> None:
    """chunk_writes_near returns writes on the named chunks with from <= t <= to, in time order."""
    store.append(
        [
            ev.chunk("r1", t0, 1, 2),
            ev.chunk("r2", t0 + 1000, 1, 2),
            ev.chunk("r1", t0 + 500, 2, 1),
            ev.chunk("r3", t0 + 2000, 3, 3),
            ev.chunk("r1", t0 + 3000, 1, 2),
        ]
    )
    rows = store.chunk_writes_near([(1, 2), (3, 3)], t0, t0 + 2000)
    assert [(r.robot_id, r.ts_ms - t0, r.row, r.column) for r in rows] == [
        ("r1", 0, 1, 2),
        ("r2", 1000, 1, 2),
        ("r3", 2000, 3, 3),
    ]
    assert rows[0].content_hash == store.chunk_events(t0, t0 + 1)[0].content_hash
    assert store.chunk_writes_near([], t0, t0 + 5000) == []


def test_the_conflict_inspectors_one_call_over_every_store(store, ev, t0) -> None:
    """GET /api/v1/conflicts over each store, the conflicts recorded as the processors do:
    both writes' robots, times and content hashes and the seek time just after the later
    write, where the map holds it; the map uploader's write under them is in no conflict."""
    from fastapi.testclient import TestClient

    from mapservice.adapters.clock import ManualClock
    from mapservice.api.app import create_app
    from mapservice.processors.conflict_recorder import record_conflicts
    from mapservice.settings import Settings

    black, white, grey = bytes(10_000), bytes([254]) * 10_000, bytes([205]) * 10_000
    writes = [
        ev.chunk("map-upload", t0 - 10_000, 1, 2, grey),
        ev.chunk("a", t0, 1, 2, black),
        ev.chunk("b", t0 + 5_000, 1, 2, white),
    ]
    store.append(writes)
    record_conflicts(store, store.chunk_writes_near([(1, 2)], t0 - 20_000, t0 + 20_000), 60_000)
    client = TestClient(create_app(Settings(), store, {}, ManualClock(t0 + 60_000)))
    body = client.get("/api/v1/conflicts", params={"from": t0 - 60_000, "to": t0 + 60_000}).json()
    assert body["conflicts"] == [
        {
            "row": 1,
            "column": 2,
            "ts_ms": t0 + 5_000,
            "robot_a": "a",
            "ts_a_ms": t0,
            "hash_a": content_hash(black).hex(),
            "robot_b": "b",
            "hash_b": content_hash(white).hex(),
            "seek_ms": t0 + 5_001,
        }
    ]
    assert store.conflicts(t0 - 60_000, t0 + 60_000) == [
        ConflictRow(1, 2, t0 + 5_000, "a", t0, "b")
    ]
    at_seek = {(c.row, c.column): c.content_hash for c in store.map_at(t0 + 5_001)}
    assert at_seek[(1, 2)] == content_hash(white).hex()
