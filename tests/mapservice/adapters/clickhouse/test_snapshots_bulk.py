"""build_snapshots_bulk builds exactly the snapshot rows build_snapshots builds, whatever the
events, their lateness and re-deliveries, the snapshots built before and the run length."""

from __future__ import annotations

import itertools
import time

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.core.events import ChunkUpdated, PoseReported, make_envelope
from mapservice.core.wire2019 import content_hash
from tests.conftest import clone_migrated

EVERY_MS = 60_000
SPAN_MS = 10 * EVERY_MS
_db = itertools.count()


def _event(e, base: int):
    if e[0] == "chunk":
        _, robot, t, row, col, shade = e
        payload = ChunkUpdated(row, col, 4, 4, b"", content_hash(bytes([shade]) * 16))
    else:
        _, robot, t, x = e
        payload = PoseReported((float(x), 0.5, 0.0), (0.0, 0.0, 0.0, 1.0), 50.0)
    return make_envelope(robot, base + t, base + t, payload)


events = st.lists(
    st.one_of(
        st.tuples(
            st.just("chunk"),
            st.sampled_from("abc"),
            st.integers(0, SPAN_MS),
            st.integers(0, 3),
            st.integers(0, 3),
            st.integers(0, 5),
        ),
        st.tuples(
            st.just("pose"), st.sampled_from("abc"), st.integers(0, SPAN_MS), st.integers(-5, 5)
        ),
    ),
    min_size=1,
    max_size=40,
)


def _rows(store) -> tuple:
    def q(sql):
        return store.client.query(sql.format(db=store.database)).result_rows

    return (
        q(
            "SELECT snap_ts, row, col, ts, robot_id, content_hash FROM {db}.map_snapshots FINAL "
            "ORDER BY ALL"
        ),
        q("SELECT snap_ts, robot_id, ts FROM {db}.robot_snapshots FINAL ORDER BY ALL"),
        q("SELECT snap_ts, chunks, robots FROM {db}.snapshot_log FINAL ORDER BY ALL"),
    )


@settings(
    max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    first=events,
    late=events,
    middle=st.integers(-1, SPAN_MS // EVERY_MS),
    per_query=st.integers(1, 12),
    redeliver=st.booleans(),
)
def test_bulk_equals_one_by_one(chdb_dir, first, late, middle, per_query, redeliver):
    """Same history and earlier snapshots: bulk and one-by-one give identical snapshot rows."""
    base = (time.time_ns() // 1_000_000 // EVERY_MS) * EVERY_MS - 2 * 3_600_000
    one = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"bulk_{next(_db)}", snapshot_every_ms=EVERY_MS
    )
    bulk = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"bulk_{next(_db)}", snapshot_every_ms=EVERY_MS
    )
    batch1 = list({e.event_id: e for e in (_event(e, base) for e in first)}.values())
    batch2 = [
        e for e in (_event(e, base) for e in late) if e.event_id not in {x.event_id for x in batch1}
    ]
    batch2 = list({e.event_id: e for e in batch2}.values())
    try:
        for s in (one, bulk):
            clone_migrated(chdb_dir, s.database)  # each example: new databases, migrated
            s.migrate()
            s.append(batch1)
            if middle >= 0:  # some snapshots exist before the bulk build
                s.build_snapshots(base + middle * EVERY_MS)
            # Events at or before those snapshots arrive late (they trigger a rebuild).
            s.append(batch2 + (batch1[:3] if redeliver else []))
        assert bulk.build_snapshots_bulk(
            base + SPAN_MS, per_query=per_query
        ) == one.build_snapshots(base + SPAN_MS)
        assert _rows(bulk) == _rows(one)
    finally:
        one.close()
        bulk.close()


def test_robots_at_mixes_recent_and_silent_robots(chdb_dir):
    """robots_at after a snapshot: robots that reported since it and robots silent since."""
    base = (time.time_ns() // 1_000_000 // EVERY_MS) * EVERY_MS - 2 * 3_600_000
    store = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"bulk_{next(_db)}", snapshot_every_ms=EVERY_MS
    )
    clone_migrated(chdb_dir, store.database)
    try:
        store.migrate()
        store.append(
            [
                _event(("pose", "c", 1000, 1), base),
                _event(("pose", "a", 2000, 2), base),
                _event(("pose", "a", 3000, 3), base),
                _event(("pose", "b", 4000, 4), base),
            ]
        )
        assert store.build_snapshots_bulk(base + EVERY_MS) == 2
        store.append([_event(("pose", "b", EVERY_MS + 500, 5), base)])
        got = [(p.robot_id, p.ts_ms - base, p.x) for p in store.robots_at(base + EVERY_MS + 900)]
        assert got == [("a", 3000, 3.0), ("b", EVERY_MS + 500, 5.0), ("c", 1000, 1.0)]
        got = [(p.robot_id, p.ts_ms - base) for p in store.robots_at(base + EVERY_MS + 100)]
        assert got == [("a", 3000), ("b", 4000), ("c", 1000)]
        assert store.robots_at(base + 999) == []
    finally:
        store.close()
