"""The store contract, retention role (`RetentionKeeper`): retention that keeps state, in
short (the long run: test_store_retention.py).

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py; shared helpers are in store_contract.py beside this module.
Times are taken from the wall clock (an hour ago, `t0`), because the ClickHouse tables drop
parts older than the retention.
"""

from __future__ import annotations

from tests.conftest import sparse_snapshots

# --- retention that keeps state (the long run: test_store_retention.py) ------------------

RET_T0 = 1_767_225_600_000  # 2026-01-01T00:00Z: long past, only the store's clock counts
DAY_MS = 86_400_000


def _retention_history(store, ev):
    """A floor written once (3 chunks), a pallet rewritten daily for ten days, a robot that
    reported once at the start and one that reports daily; the events, for the fold."""
    sparse_snapshots(store)  # 40 snapshots for ten days, not 1,440
    written = [ev.chunk("mapper", RET_T0 + 1000, r, 0, bytes([r]) * 10_000) for r in range(3)]
    written += [
        ev.chunk("amr", RET_T0 + d * DAY_MS + 5000, 3, 3, bytes([50 + d]) * 10_000)
        for d in range(10)
    ]
    store.append(
        [
            ev.meta(RET_T0),
            *written,
            ev.pose("quiet", RET_T0 + 3_600_000),
            *(ev.pose("busy", RET_T0 + d * DAY_MS + 7000) for d in range(10)),
        ]
    )
    return written


def _fold(written, at_ms):
    from mapservice.core.timetravel import fold_map

    class W:
        def __init__(self, e):
            self.row, self.column, self.ts_ms = e.payload.row, e.payload.column, e.event_time_ms
            self.robot_id, self.content_hash = e.robot_id, e.payload.content_hash.hex()

    return {k: v.content_hash for k, v in fold_map([W(e) for e in written], at_ms).items()}


def test_retention_keeps_the_floor_its_pixels_the_robots_and_the_meta(store, ev) -> None:
    written = _retention_history(store, ev)
    now = RET_T0 + 10 * DAY_MS
    done = store.apply_retention(now)
    assert done.partitions_dropped > 0 and done.first_day_kept is not None
    assert store.chunk_events(0, now - 8 * DAY_MS) == []  # the old days are gone
    for t in (now - 7 * DAY_MS, now - 3 * DAY_MS, now):
        got = {(c.row, c.column): c.content_hash for c in store.map_at(t)}
        assert got == _fold(written, t)
        named = [bytes.fromhex(h) for h in got.values()]
        assert set(store.chunk_contents(named)) == set(named)
    assert {p.robot_id for p in store.robots_at(now)} == {"quiet", "busy"}
    assert store.robots_at(now)[1].ts_ms == RET_T0 + 3_600_000  # quiet's last pose, carried
    assert store.latest_meta() is not None


def test_retention_twice_and_a_late_write_after_it_keep_the_floor(store, ev) -> None:
    written = _retention_history(store, ev)
    now = RET_T0 + 10 * DAY_MS
    store.build_snapshots(now)
    store.apply_retention(now)
    again = store.apply_retention(now)
    assert again.partitions_dropped == 0 and again.contents_renewed == 0
    late = ev.chunk("late", now - 3 * DAY_MS, 0, 0, bytes([99]) * 10_000)
    store.append([late])
    written.append(late)
    while store.repair_snapshots():
        pass
    for t in (now - 7 * DAY_MS, now - 3 * DAY_MS, now):
        assert {(c.row, c.column): c.content_hash for c in store.map_at(t)} == _fold(written, t)
    # Eleven more days: the renewed floor is renewed again, and the late write's pixels kept.
    later = now + 11 * DAY_MS
    store.append([ev.pose("busy", later - 1000)])
    store.build_snapshots(later)
    store.apply_retention(later)
    got = {(c.row, c.column): c.content_hash for c in store.map_at(later)}
    assert got == _fold(written, later)
    named = [bytes.fromhex(h) for h in got.values()]
    assert set(store.chunk_contents(named)) == set(named)


def test_a_late_write_at_the_retention_boundary_is_folded_into_the_carried_floor(store, ev) -> None:
    """The snapshot that carries the floor has no events before it any more: a late write at
    its instant is folded in (ClickHouse refolds that snapshot from its own rows) and the
    rest of the floor stays."""
    written = _retention_history(store, ev)
    now = RET_T0 + 10 * DAY_MS
    store.build_snapshots(now)
    store.apply_retention(now)
    late = ev.chunk("late", now - 7 * DAY_MS, 1, 0, bytes([77]) * 10_000)
    store.append([late])
    written.append(late)
    while store.repair_snapshots():
        pass
    for t in (now - 7 * DAY_MS, now - DAY_MS, now):
        assert {(c.row, c.column): c.content_hash for c in store.map_at(t)} == _fold(written, t)
