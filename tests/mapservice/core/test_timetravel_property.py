"""Snapshot plus events equals a brute-force fold, whatever the order, lateness,
duplication and snapshot timing of the events (ClickHouse through chDB)."""

from __future__ import annotations

import itertools
import time

from fastapi.testclient import TestClient
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.api.app import create_app
from mapservice.core.events import ChunkUpdated, PoseReported, make_envelope
from mapservice.core.ports import ChunkState
from mapservice.core.timetravel import fold_map, fold_robots
from mapservice.core.wire2019 import content_hash
from mapservice.settings import Settings
from tests.conftest import clone_migrated

EVERY_MS = 60_000
SPAN_MS = 10 * EVERY_MS
_db = itertools.count()


def chunk(robot: str, ts: int, row: int, col: int, shade: int):
    pixels = bytes([shade]) * 16
    payload = ChunkUpdated(row, col, 4, 4, b"", content_hash(pixels))
    return make_envelope(robot, ts, ts, payload)


def pose(robot: str, ts: int, x: float):
    return make_envelope(robot, ts, ts, PoseReported((x, 0.5, 0.0), (0.0, 0.0, 0.0, 1.0), 50.0))


event_strategy = st.one_of(
    st.builds(
        lambda r, t, row, col, shade: ("chunk", r, t, row, col, shade),
        st.sampled_from(["a", "b", "c"]),
        st.integers(0, SPAN_MS),
        st.integers(0, 2),
        st.integers(0, 2),
        st.integers(0, 3),
    ),
    st.builds(
        lambda r, t, x: ("pose", r, t, x),
        st.sampled_from(["a", "b", "c"]),
        st.integers(0, SPAN_MS),
        st.integers(-5, 5),
    ),
)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    events=st.lists(event_strategy, min_size=1, max_size=40),
    batch_cuts=st.lists(st.integers(1, 40), max_size=6),
    snapshot_points=st.lists(st.integers(0, SPAN_MS), min_size=1, max_size=4),
    duplicates=st.lists(st.integers(0, 39), max_size=6),
    queries=st.lists(st.integers(-EVERY_MS, SPAN_MS + EVERY_MS), min_size=1, max_size=6),
)
# A chunk write and a pose that arrive after the snapshots covering them were built.
@example(
    events=[
        ("chunk", "a", 1000, 0, 0, 1),
        ("pose", "b", 1000, 1),
        ("chunk", "a", 2000, 0, 0, 2),
        ("pose", "b", 2000, 2),
    ],
    batch_cuts=[2],
    snapshot_points=[5 * EVERY_MS],
    duplicates=[],
    queries=[3 * EVERY_MS],
)
def test_state_at_t_equals_brute_force_fold(
    chdb_dir, events, batch_cuts, snapshot_points, duplicates, queries
):
    """For random T, the API's map at T and robots at T (and the store's) equal a fold of
    every stored event with time <= T."""
    base = (time.time_ns() // 1_000_000 // EVERY_MS) * EVERY_MS - 2 * 3_600_000
    store = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"tt_{next(_db)}", snapshot_every_ms=EVERY_MS
    )
    clone_migrated(chdb_dir, store.database)  # each example: a new database, migrated
    store.migrate()
    envs = [
        chunk(e[1], base + e[2], e[3], e[4], e[5])
        if e[0] == "chunk"
        else pose(e[1], base + e[2], float(e[3]))
        for e in events
    ]
    # Same-identity writes must be identical re-deliveries, as QoS 1 produces them.
    unique = {env.event_id: env for env in envs}
    envs = [unique[env.event_id] for env in envs]
    envs += [envs[i % len(envs)] for i in duplicates]  # re-deliveries
    cuts = sorted({c % (len(envs) + 1) for c in batch_cuts} | {0, len(envs)})
    snaps = iter(sorted(base + p for p in snapshot_points))
    for lo, hi in zip(cuts, cuts[1:]):
        store.append(envs[lo:hi])  # arrival order: as generated, so late events happen
        upto = next(snaps, None)
        if upto is not None:
            store.build_snapshots(upto)
    store.build_snapshots(base + SPAN_MS)

    chunks = [e for e in envs if isinstance(e.payload, ChunkUpdated)]
    rows = [
        ChunkState(
            e.payload.row,
            e.payload.column,
            e.event_time_ms,
            e.robot_id,
            e.payload.content_hash.hex(),
        )
        for e in chunks
    ]
    pose_times = {}
    for e in envs:
        if isinstance(e.payload, PoseReported):
            pose_times[(e.robot_id, e.event_time_ms)] = e
    api = TestClient(create_app(Settings(), store))
    for q in queries:
        at = base + q
        expected = fold_map(rows, at)
        assert {(c.row, c.column): c for c in store.map_at(at)} == expected
        served = api.get("/api/v1/map", params={"at": at}).json()["chunks"]
        assert {
            (c["row"], c["column"]): ChunkState(
                c["row"], c["column"], c["ts_ms"], c["robotId"], c["content_hash"]
            )
            for c in served
        } == expected
        expected_robots = {}
        for (robot, ts), e in pose_times.items():
            if ts <= at and ts > expected_robots.get(robot, (-1, None))[0]:
                expected_robots[robot] = (ts, e.payload.position[0])
        got = {p.robot_id: (p.ts_ms, p.x) for p in store.robots_at(at)}
        assert got == expected_robots
        served_robots = api.get("/api/v1/robots", params={"at": at}).json()["robots"]
        assert {
            r["robotId"]: (r["ts_ms"], r["position"][0]) for r in served_robots
        } == expected_robots
    store.close()


def test_fold_map_prefers_latest_time_then_robot_id():
    """The pure fold keeps the greatest (event time, robot id) per chunk and ignores later ones."""
    rows = [
        ChunkState(0, 0, 10, "b", "x"),
        ChunkState(0, 0, 10, "a", "y"),
        ChunkState(0, 0, 30, "a", "z"),
        ChunkState(1, 0, 5, "a", "w"),
    ]
    assert fold_map(rows, 20) == {(0, 0): rows[0], (1, 0): rows[3]}
    assert fold_map(rows, 4) == {}


def test_fold_robots_keeps_latest_pose_at_or_before_t():
    """Robots at T: each robot's newest pose with time <= T."""
    from mapservice.core.ports import PoseRow

    def p(robot, ts):
        return PoseRow(robot, ts, 0, 0, 0, 0, 0, 0, 1, None, None, None, None, ts)

    poses = [p("a", 5), p("a", 15), p("b", 20)]
    assert fold_robots(poses, 10) == {"a": poses[0]}
    assert fold_robots(poses, 20) == {"a": poses[1], "b": poses[2]}
