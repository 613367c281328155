"""The bulk history loader: rows per table, times, positions, snapshots and time travel.

One chDB engine for the module (one database per load); every load ends a few minutes
ago, so the TTL of the seven-day retention never drops a row while a test reads it.
"""

from __future__ import annotations

import itertools
import time
import zlib

import numpy as np
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import load_ros_map
from mapservice.bench.history_generator import DAY_MS, circle_centres, pixel_of
from mapservice.bench.history_loader import TTL_GUARD_MS, load_history, plan_window
from mapservice.core.events import ChunkUpdated, PoseReported, make_envelope
from mapservice.core.timetravel import fold_map, fold_robots
from mapservice.core.wire2019 import content_hash
from tests.conftest import clone_migrated

MAP = "maps/warehouse.yaml"
EVERY_MS = 60_000
ROBOTS = 2
SECONDS = 600
_db = itertools.count()


@pytest.fixture(scope="module")
def ros_map():
    """The warehouse map the loader drives robots on."""
    return load_ros_map(MAP)


@pytest.fixture(scope="module")
def end_ms() -> int:
    """The end of every load in the module: five minutes ago, so the loads are identical."""
    return time.time_ns() // 1_000_000 - 300_000


def _store(path) -> ClickHouseStore:
    return ClickHouseStore(
        f"chdb://{path}", database=f"loader_{next(_db)}", snapshot_every_ms=EVERY_MS
    )


def _load(path, ros_map, end_ms, **kw):
    """A load into a new database: cloned from the module's migrated template, so the
    loader's own migrate() finds every migration applied (test_cli_load_history loads into
    a database the loader migrates)."""
    store = _store(path)
    clone_migrated(path, store.database)
    result = load_history(
        store,
        ros_map,
        days=SECONDS / 86_400,
        robots=ROBOTS,
        end_ms=end_ms,
        grid=kw.pop("grid", (4, 6)),
        change_prob=kw.pop("change_prob", 0.2),
        **kw,
    )
    return store, result


@pytest.fixture(scope="module")
def loaded(chdb_dir, ros_map, end_ms):
    """2 robots x 10 minutes on a 4 x 6 grid, snapshots every minute (bulk)."""
    store, result = _load(chdb_dir, ros_map, end_ms)
    yield store, result
    store.close()


def _q(store, sql: str, **kw) -> list[tuple]:
    return store.client.query(sql.format(db=store.database), **kw).result_rows


def test_row_counts_per_table(loaded) -> None:
    """One pose a second and one chunk every five seconds per robot; one content row per hash."""
    store, result = loaded
    assert (result.poses, result.chunk_events) == (ROBOTS * SECONDS, ROBOTS * SECONDS // 5)
    counts = store.counts()
    assert (counts.poses, counts.chunk_events) == (ROBOTS * SECONDS, ROBOTS * SECONDS // 5)
    used = _q(store, "SELECT uniqExact(content_hash, toDate(ts)) FROM {db}.chunk_events")[0][0]
    assert (
        _q(store, "SELECT count() FROM {db}.chunk_contents")[0][0] == used == result.chunk_contents
    )
    # Variety: changed pixels add contents beyond the map's own chunks.
    assert counts.chunk_contents > 20
    assert (
        _q(
            store,
            "SELECT count() FROM {db}.chunk_events WHERE content_hash NOT IN "
            "(SELECT content_hash FROM {db}.chunk_contents)",
        )[0][0]
        == 0
    )
    meta = store.latest_meta()
    assert (meta.chunk_rows, meta.chunk_cols, meta.width, meta.height) == (4, 6, 600, 400)


def test_contents_are_zlib_chunks_with_their_hash(loaded) -> None:
    """Every stored content inflates to 100 x 100 pixels whose blake2b-128 is its hash."""
    store, _ = loaded
    rows = _q(
        store,
        "SELECT content_hash, width, height, zlib_pixels FROM {db}.chunk_contents",
        column_formats={"zlib_pixels": "bytes", "content_hash": "bytes"},
    )
    for h, w, height, data in rows:
        pixels = zlib.decompress(bytes(data))
        assert (w, height, len(pixels)) == (100, 100, 10_000)
        assert content_hash(pixels) == bytes(h)


def test_times_lie_in_the_window_at_the_2019_rates(loaded, end_ms) -> None:
    """Times are in [start, end) inside the retention; poses 1 s apart, chunks on every 5th."""
    store, result = loaded
    assert result.end_ms <= end_ms
    assert result.end_ms - result.start_ms == SECONDS * 1000
    assert result.start_ms >= time.time_ns() // 1_000_000 - 7 * DAY_MS
    poses = store.poses(0, 2**62)
    chunks = store.chunk_events(0, 2**62)
    assert all(result.start_ms <= p.ts_ms < result.end_ms for p in poses)
    assert all(result.start_ms <= c.ts_ms < result.end_ms for c in chunks)
    for robot in {p.robot_id for p in poses}:
        ts = [p.ts_ms for p in poses if p.robot_id == robot]
        assert len(ts) == SECONDS
        assert all(950 <= b - a <= 1050 for a, b in zip(ts, ts[1:]))
        assert [c.ts_ms for c in chunks if c.robot_id == robot] == ts[4::5]
    assert all(0 <= c.row < 4 and 0 <= c.column < 6 for c in chunks)
    assert all(p.receive_time_ms > p.ts_ms for p in poses)


def test_each_pose_is_on_a_free_cell(loaded, ros_map) -> None:
    """Every stored position falls on a free pixel of the map, and robots really move."""
    store, _ = loaded
    poses = store.poses(0, 2**62)
    rows, cols = pixel_of(ros_map, np.array([p.x for p in poses]), np.array([p.y for p in poses]))
    assert (ros_map.pixels[rows, cols] >= 250).all()
    for robot in {p.robot_id for p in poses}:
        xy = np.array([(p.x, p.y) for p in poses if p.robot_id == robot])
        assert np.ptp(xy[:, 0]) > 1.5 and np.ptp(xy[:, 1]) > 1.5  # a 1 m circle


def test_circle_centres_keep_the_whole_circle_free(ros_map) -> None:
    """Points all around each chosen centre's 1 m circle land on free pixels."""
    centres = circle_centres(ros_map)
    assert len(centres) > 100
    angles = np.linspace(0, 2 * np.pi, 2000)
    for cx, cy in centres[:: max(1, len(centres) // 200)]:
        x = np.round((cx + np.cos(angles)) * 1000) / 1000
        y = np.round((cy + np.sin(angles)) * 1000) / 1000
        rows, cols = pixel_of(ros_map, x, y)
        assert (ros_map.pixels[rows, cols] >= 250).all()


def _snapshot_rows(store) -> tuple[list, list, list]:
    return (
        _q(
            store,
            "SELECT snap_ts, row, col, ts, robot_id, hex(content_hash) "
            "FROM {db}.map_snapshots FINAL ORDER BY ALL",
        ),
        _q(store, "SELECT snap_ts, robot_id, ts FROM {db}.robot_snapshots FINAL ORDER BY ALL"),
        _q(store, "SELECT snap_ts, chunks, robots FROM {db}.snapshot_log FINAL ORDER BY ALL"),
        _q(store, "SELECT second, offsets FROM {db}.chunk_seconds FINAL ORDER BY ALL"),
    )


def _derived_rows(store) -> tuple[list, ...]:
    """What the materialized views and the snapshot builders derived from the events."""
    return (
        _q(store, "SELECT * FROM {db}.pose_keyframes FINAL ORDER BY robot_id, ts"),
        _q(
            store,
            "SELECT cell, robot_id, min(first_ts), max(last_ts) FROM {db}.pose_minutes "
            "GROUP BY ALL ORDER BY ALL",
        ),
        _q(
            store,
            "SELECT cell, robot_id, min(first_ts), max(last_ts) FROM {db}.pose_ten_minutes "
            "GROUP BY ALL ORDER BY ALL",
        ),
        _q(store, "SELECT second, offsets FROM {db}.chunk_seconds FINAL ORDER BY ALL"),
    )


def test_loader_derives_the_rows_live_ingest_derives(loaded, chdb_dir) -> None:
    """The loader's day-sized inserts fill pose_keyframes, pose_(ten_)minutes and chunk_seconds
    with exactly the rows the same events appended in the sink's small batches give."""
    store, result = loaded
    live = _store(chdb_dir)
    clone_migrated(chdb_dir, live.database)
    try:
        live.migrate()
        events = [
            make_envelope(
                p.robot_id,
                p.ts_ms,
                p.receive_time_ms,
                PoseReported(
                    (p.x, p.y, p.z),
                    (p.qx, p.qy, p.qz, p.qw),
                    p.battery_level,
                    p.charging,
                    p.loaded,
                    p.path,
                ),
            )
            for p in store.poses(0, 2**62)
        ]
        events += [
            make_envelope(
                c.robot_id,
                c.ts_ms,
                c.receive_time_ms,
                ChunkUpdated(c.row, c.column, 100, 100, b"", bytes.fromhex(c.content_hash)),
            )
            for c in store.chunk_events(0, 2**62)
        ]
        events.sort(key=lambda e: e.event_time_ms)
        for i in range(0, len(events), 50):  # about a second of a 50-robot fleet per batch
            live.append(events[i : i + 50])
        live.build_snapshots(result.end_ms)
        derived = _derived_rows(store)
        assert all(len(rows) > 0 for rows in derived)
        assert derived == _derived_rows(live)
    finally:
        live.close()


def test_bulk_snapshots_equal_build_snapshots(loaded, chdb_dir, ros_map, end_ms) -> None:
    """The loader's bulk snapshots are the rows build_snapshots builds for the same history."""
    store, result = loaded
    other, again = _load(chdb_dir, ros_map, end_ms, bulk_snapshots=False)
    try:
        assert (again.poses, again.chunk_events) == (result.poses, result.chunk_events)
        assert again.snapshots == result.snapshots == SECONDS // 60 + 1
        bulk, one_by_one = _snapshot_rows(store), _snapshot_rows(other)
        assert len(bulk[0]) > 0 and len(bulk[1]) >= ROBOTS * (len(bulk[2]) - 1)
        assert bulk == one_by_one
    finally:
        other.close()


def test_bulk_snapshots_continue_existing_ones_in_runs(chdb_dir, ros_map, end_ms) -> None:
    """After snapshots built one by one, bulk runs of 3 give the rows a one-by-one build does."""
    a, result = _load(chdb_dir, ros_map, end_ms, snapshots=False)
    b, _ = _load(chdb_dir, ros_map, end_ms, snapshots=False)
    try:
        middle = result.start_ms + 4 * EVERY_MS
        assert a.build_snapshots(middle) == b.build_snapshots(middle) > 0
        assert a.build_snapshots_bulk(result.end_ms, per_query=3) == b.build_snapshots(
            result.end_ms
        )
        assert _snapshot_rows(a) == _snapshot_rows(b)
        assert a.build_snapshots_bulk(result.end_ms) == 0  # nothing due: nothing built
    finally:
        a.close()
        b.close()


def test_map_and_robots_at_equal_the_naive_fold(loaded) -> None:
    """map_at and robots_at over the loaded history equal a fold of every stored event."""
    store, result = loaded
    chunks = store.chunk_events(0, 2**62)
    poses = store.poses(0, 2**62)
    rng = np.random.default_rng(3)
    instants = [
        result.start_ms - 1,
        result.start_ms + EVERY_MS,
        result.end_ms,
        *rng.integers(result.start_ms, result.end_ms, 8).tolist(),
    ]
    for at in instants:
        assert {(c.row, c.column): c for c in store.map_at(at)} == fold_map(chunks, at)
        assert store.robots_at(at) == [v for _, v in sorted(fold_robots(poses, at).items())]


def test_loader_refuses_a_database_with_history(loaded, ros_map) -> None:
    """Loading into a database that already holds history is refused."""
    store, _ = loaded
    with pytest.raises(ValueError, match="already holds"):
        load_history(store, ros_map, days=0.001, robots=1)


def test_window_stays_inside_the_retention() -> None:
    """A window reaching past the retention starts later (TTL guard); a future end is refused."""
    now = 1_795_255_200_000
    start, end, notes = plan_window(7, now, 7, now_ms=now)
    assert end == now and start == now - 7 * DAY_MS + TTL_GUARD_MS and notes
    start, end, notes = plan_window(0.5, now - 1234, 7, now_ms=now)
    assert (end, end - start, notes) == (now - 2000, DAY_MS // 2, [])
    with pytest.raises(ValueError):
        plan_window(1, now + 60_000, 7, now_ms=now)


def test_cli_load_history(chdb_dir, capsys) -> None:
    """`mapservice load-history` loads through the CLI and reports what it wrote."""
    from mapservice.cli import main

    main(
        [
            "load-history",
            "--days",
            "0.002",
            "--robots",
            "3",
            "--map",
            MAP,
            "--data-dir",
            str(chdb_dir.parent),
            "--clickhouse-dsn",
            f"chdb://{chdb_dir}",
            "--database",
            "loader_cli",
            "--snapshot-every-s",
            "60",
        ]
    )
    out = capsys.readouterr().out
    assert "loaded 516 poses" in out
    store = ClickHouseStore(f"chdb://{chdb_dir}", database="loader_cli")
    try:
        assert store.counts().poses == 3 * 172
        assert _q(store, "SELECT count() FROM {db}.snapshot_log")[0][0] >= 2
    finally:
        store.close()
