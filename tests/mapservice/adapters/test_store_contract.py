"""One contract for every HistoryStore: MemoryStore, ClickHouseStore on embedded chDB, and
ClickHouseStore on a ClickHouse server's HTTP interface (the split deployment's path: here
`mapservice clickhouse-server`'s app over the same chDB, served from this process).

The `store` fixture (tests/conftest.py) gives each test an empty, migrated store of each
kind; the ClickHouse kinds are databases of their own in the module's one chDB engine
(`chdb_dir`), which the chDB-only tests below open directly. Times are taken from the wall clock (an hour
ago), because the ClickHouse tables drop parts older than the retention.
"""

from __future__ import annotations

import itertools
import os
import time
import zlib

import numpy as np
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.testing.memory_store import MemoryStore
from mapservice.core.events import PoseReported, make_envelope
from mapservice.core.legacy_query import parse_chunk_query, parse_pose_query
from mapservice.core.ports import ChunkRow, ConflictRow, Counts, PoseRow
from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.core.wire2019 import content_hash

_databases = itertools.count()


def _clickhouse(chdb_dir) -> ClickHouseStore:
    return ClickHouseStore(f"chdb://{chdb_dir}", database=f"contract_{next(_databases)}")


@pytest.fixture
def t0() -> int:
    """A whole second an hour ago (inside the retention, so no TTL can drop the rows)."""
    return (time.time_ns() // 1_000_000 // 1000) * 1000 - 3_600_000


def _random_pixels(seed: int, n: int = 100 * 100) -> bytes:
    # Incompressible pixels make zlib bytes that are not valid UTF-8.
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


# --- schema -----------------------------------------------------------------------------


def test_migrate_returns_version_and_is_repeatable(store, ev, t0) -> None:
    """migrate() returns the schema version, and running it again keeps the data."""
    store.append([ev.pose("r1", t0)])
    assert store.migrate() == SCHEMA_VERSION
    assert store.migrate() == SCHEMA_VERSION
    assert store.counts().poses == 1


# --- idempotent appends ------------------------------------------------------------------


def test_append_twice_yields_one_row_each(store, ev, t0) -> None:
    """Appending the same events twice (a redelivered batch) leaves one row per event."""
    batch = [ev.pose("r1", t0), ev.pose("r2", t0), ev.chunk("r1", t0, 1, 1),
             ev.meta(t0)]
    store.append(batch)
    store.append(batch)
    store.append(batch[:1] * 3)
    assert store.counts() == Counts(poses=2, chunk_events=1, chunk_contents=1, dead_letters=0)
    assert len(store.poses(t0, t0 + 1)) == 2
    assert len(store.chunk_events(t0, t0 + 1)) == 1


def test_same_identity_keeps_one_row_with_the_last_write(store, ev, t0) -> None:
    """Two poses with one robot and time are one row, holding the later write."""
    store.append([ev.pose("r1", t0, x=1.0)])
    store.append([ev.pose("r1", t0, x=2.0)])
    rows = store.poses(t0, t0 + 1)
    assert [(r.robot_id, r.x) for r in rows] == [("r1", 2.0)]


def test_chunk_identity_includes_robot_and_cell(store, ev, t0) -> None:
    """Chunk writes differing only in robot, row or column are separate rows."""
    store.append([ev.chunk("r1", t0, 0, 0), ev.chunk("r2", t0, 0, 0), ev.chunk("r1", t0, 0, 1),
                  ev.chunk("r1", t0, 1, 0)])
    assert store.counts().chunk_events == 4


def test_empty_appends_are_harmless(store) -> None:
    """Empty batches change nothing."""
    store.append([])
    store.append_dead_letters([])
    assert store.counts() == Counts(0, 0, 0, 0)


# --- conflicts ----------------------------------------------------------------------------


def _conflict(t0: int, dt: int, robot_a: str = "a", robot_b: str = "b", dt_a: int = 0,
              row: int = 1, column: int = 2):
    from mapservice.core.ports import ConflictRow
    return ConflictRow(row, column, t0 + dt, robot_a, t0 + dt_a, robot_b)


def test_conflicts_window_order_and_idempotence(store, t0) -> None:
    """conflicts(from, to) holds from <= ts < to in identity order; a repeat adds no row."""
    rows = [_conflict(t0, 2000, "c", "d"), _conflict(t0, 1000), _conflict(t0, 1000, row=0),
            _conflict(t0, 5000)]
    store.append_conflicts(rows)
    store.append_conflicts(rows[:2])
    store.append_conflicts([])
    got = store.conflicts(t0, t0 + 5000)
    assert [(c.ts_ms - t0, c.row, c.robot_a) for c in got] == [(1000, 0, "a"), (1000, 1, "a"),
                                                               (2000, 1, "c")]
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
    store.append([ev.chunk("r1", t0, 1, 2), ev.chunk("r2", t0 + 1000, 1, 2),
                  ev.chunk("r1", t0 + 500, 2, 1), ev.chunk("r3", t0 + 2000, 3, 3),
                  ev.chunk("r1", t0 + 3000, 1, 2)])
    rows = store.chunk_writes_near([(1, 2), (3, 3)], t0, t0 + 2000)
    assert [(r.robot_id, r.ts_ms - t0, r.row, r.column) for r in rows] == [
        ("r1", 0, 1, 2), ("r2", 1000, 1, 2), ("r3", 2000, 3, 3)]
    assert rows[0].content_hash == store.chunk_events(t0, t0 + 1)[0].content_hash
    assert store.chunk_writes_near([], t0, t0 + 5000) == []


# --- windows, order, filters -------------------------------------------------------------


def test_pose_window_is_half_open_and_ordered(store, ev, t0) -> None:
    """poses(from, to) holds from <= t < to, ordered by time then robot."""
    store.append([ev.pose("r2", t0 + 1000), ev.pose("r1", t0 + 2000), ev.pose("r1", t0 + 1000),
                  ev.pose("r3", t0), ev.pose("r1", t0 - 1)])
    rows = store.poses(t0, t0 + 2000)
    assert [(r.ts_ms - t0, r.robot_id) for r in rows] == [(0, "r3"), (1000, "r1"), (1000, "r2")]
    rows = store.poses(t0 + 1, t0 + 2001)
    assert [(r.ts_ms - t0, r.robot_id) for r in rows] == [(1000, "r1"), (1000, "r2"),
                                                          (2000, "r1")]
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
    store.append([ev.chunk("r1", t0 + 500, 2, 0), ev.chunk("r1", t0, 1, 1),
                  ev.chunk("r2", t0 + 500, 0, 3), ev.chunk("r1", t0 + 1000, 0, 0),
                  ev.chunk("r1", t0 - 1, 0, 0)])
    rows = store.chunk_events(t0, t0 + 1000)
    assert [(r.ts_ms - t0, r.row, r.column, r.robot_id) for r in rows] == [
        (0, 1, 1, "r1"), (500, 0, 3, "r2"), (500, 2, 0, "r1")]
    assert [r.ts_ms - t0 for r in store.chunk_events(t0 + 1, t0 + 1001)] == [500, 500, 1000]
    assert len(store.chunk_events(t0, t0 + 1000, limit=1)) == 1


def test_chunk_row_fields(store, ev, t0) -> None:
    """A chunk row carries cell, robot, hex content hash and the receive time."""
    pixels = _random_pixels(1)
    store.append([ev.chunk("r7", t0, 4, 5, pixels, receive_lag_ms=321)])
    assert store.chunk_events(t0, t0 + 1) == [
        ChunkRow(row=4, column=5, ts_ms=t0, robot_id="r7", content_hash=content_hash(pixels).hex(),
                 receive_time_ms=t0 + 321)]


# --- chunk contents ----------------------------------------------------------------------


def test_chunk_content_returns_size_and_zlib_bytes(store, ev, t0) -> None:
    """chunk_content(hash) gives (width, height, the zlib bytes as sent); unknown is None."""
    pixels = _random_pixels(2, 50 * 40)
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
    same = _random_pixels(3)
    store.append([ev.chunk("r1", t0 + i, i % 3, i // 3, same) for i in range(6)])
    store.append([ev.chunk("r2", t0 + 10, 0, 0, same)])
    assert store.counts().chunk_contents == 1
    assert store.counts().chunk_events == 7
    assert {r.content_hash for r in store.chunk_events(t0, t0 + 100)} == {content_hash(same).hex()}
    store.append([ev.chunk("r2", t0 + 20, 0, 0, _random_pixels(4))])
    assert store.counts().chunk_contents == 2


# --- meta, counts, dead letters ----------------------------------------------------------


def test_latest_meta_is_the_newest(store, ev, t0) -> None:
    """latest_meta() is the meta with the latest event time, whatever the insert order."""
    assert store.latest_meta() is None
    newest = ev.meta(t0 + 5000, chunk_rows=9, chunk_cols=8)
    store.append([newest])
    store.append([ev.meta(t0, chunk_rows=2, chunk_cols=3)])
    assert store.latest_meta() == newest.payload
    assert store.latest_meta().origin == (-1.5, 2.0, 0.0)


def test_counts_count_each_kind(store, ev, t0) -> None:
    """counts() reports poses, chunk events, distinct contents and dead letters."""
    store.append([ev.pose("r1", t0 + i) for i in range(5)])
    store.append([ev.chunk("r1", t0, 0, 0, _random_pixels(5)),
                  ev.chunk("r1", t0, 0, 1, _random_pixels(6)),
                  ev.chunk("r1", t0, 0, 2, _random_pixels(5))])
    store.append_dead_letters([ev.dead_letter(t_ms=t0)])
    assert store.counts() == Counts(poses=5, chunk_events=3, chunk_contents=2, dead_letters=1)


def test_dead_letters_are_appended_and_counted(store, ev, t0) -> None:
    """Dead letters are kept as they come (even identical ones) and counted."""
    letter = ev.dead_letter("bad_zlib", payload=b"\x00\xff\xfe binary", t_ms=t0)
    store.append_dead_letters([letter, ev.dead_letter("not_json", t_ms=t0 + 1)])
    assert store.counts().dead_letters == 2
    store.append_dead_letters([letter])
    assert store.counts().dead_letters == 3
    assert store.counts().poses == 0


# --- what a pose row keeps ---------------------------------------------------------------

PRECISE = PoseReported(
    position=(1.23456, -2.0004, 0.0006),
    orientation=(0.1, -0.2, 0.30000001, 0.9273618),
    battery_level=33.3,
    charging=True,
    loaded="dfs",
    path=((1.0004, 2.0006), (-0.5, 1e-4)),
)
f32 = lambda v: float(np.float32(v))  # noqa: E731


def test_pose_precision_is_millimetres_and_float32(store, t0) -> None:
    """Positions come back to the millimetre, orientation and battery as 32-bit floats."""
    store.append([make_envelope("r1", t0, t0 + 70, PRECISE)])
    (row,) = store.poses(t0, t0 + 1)
    assert row == PoseRow(
        robot_id="r1", ts_ms=t0, x=1.235, y=-2.0, z=0.001,
        qx=f32(0.1), qy=f32(-0.2), qz=f32(0.30000001), qw=f32(0.9273618),
        battery_level=f32(33.3), charging=True, loaded="dfs",
        path=((1.0, 2.001), (-0.5, 0.0)), receive_time_ms=t0 + 70)


def test_receive_time_before_event_time_is_kept(store, ev, t0) -> None:
    """A robot clock slightly ahead (negative lag) keeps its exact receive time."""
    store.append([ev.pose("r1", t0, receive_lag_ms=-250_000),
                  ev.chunk("r1", t0, receive_lag_ms=-1)])
    assert store.poses(t0, t0 + 1)[0].receive_time_ms == t0 - 250_000
    assert store.chunk_events(t0, t0 + 1)[0].receive_time_ms == t0 - 1


@pytest.mark.parametrize("charging,loaded", [
    (True, False), (False, True), ("sdf", "dfs"), ("true", "false"), ("", "0"), (None, None),
    (True, None),
], ids=repr)
def test_flags_keep_bool_or_string_type(store, ev, t0, charging, loaded) -> None:
    """charging/loaded come back with the type the robot sent: bool stays bool, str stays str."""
    store.append([ev.pose("r1", t0, charging=charging, loaded=loaded)])
    (row,) = store.poses(t0, t0 + 1)
    assert (row.charging, row.loaded) == (charging, loaded)
    assert (type(row.charging), type(row.loaded)) == (type(charging), type(loaded))


@pytest.mark.parametrize("path", [None, (), ((3.0, 4.0),)], ids=["none", "empty", "one"])
def test_path_none_and_empty_stay_apart(store, ev, t0, path) -> None:
    """A pose without a path and one with an empty path are told apart."""
    store.append([ev.pose("r1", t0, path=path)])
    assert store.poses(t0, t0 + 1)[0].path == path


def test_battery_none_stays_none(store, ev, t0) -> None:
    """A pose without a battery level keeps None (not 0)."""
    store.append([ev.pose("r1", t0, battery_level=None)])
    assert store.poses(t0, t0 + 1)[0].battery_level is None


def test_adapters_return_identical_rows(chdb_dir, ev, t0) -> None:
    """The same events give identical pose rows, chunk rows, contents and meta in both."""
    events = [make_envelope("r1", t0, t0 + 70, PRECISE),
              make_envelope("r2", t0 + 1, t0 + 2, PoseReported(
                  position=(-123.4567, 0.0005, 10.0), orientation=(0.0, 0.0, 0.70710678, 0.70710678),
                  battery_level=None, charging="sdf", loaded=False, path=None)),
              ev.pose("r3", t0 + 2, x=0.0015, y=-0.0015),
              ev.chunk("r1", t0 + 3, 2, 3, _random_pixels(7)),
              ev.chunk("r2", t0 + 3, 2, 3, _random_pixels(7)),
              ev.meta(t0 + 4)]
    memory, clickhouse = MemoryStore(), _clickhouse(chdb_dir)
    try:
        for s in (memory, clickhouse):
            s.migrate()
            s.append(events)
        assert clickhouse.poses(t0, t0 + 10) == memory.poses(t0, t0 + 10)
        assert clickhouse.chunk_events(t0, t0 + 10) == memory.chunk_events(t0, t0 + 10)
        h = content_hash(_random_pixels(7))
        assert clickhouse.chunk_content(h) == memory.chunk_content(h)
        assert clickhouse.latest_meta() == memory.latest_meta()
        assert clickhouse.counts() == memory.counts()
    finally:
        clickhouse.close()


# --- ClickHouse specifics -----------------------------------------------------------------


def test_clickhouse_writes_content_once_per_hash_and_day(chdb_dir, ev, t0) -> None:
    """ClickHouse inserts a content's pixels once per day, not once per chunk write."""
    store = _clickhouse(chdb_dir)
    try:
        store.migrate()
        pixels = _random_pixels(8)
        for i in range(4):
            store.append([ev.chunk("r1", t0 + i, 0, i, pixels)])
        (physical,) = store.client.query(
            f"SELECT count() FROM {store.database}.chunk_contents").result_rows[0]
        assert physical == 1
    finally:
        store.close()


def test_clickhouse_store_reopens_with_its_data(chdb_dir, ev, t0) -> None:
    """A ClickHouseStore closed and opened again on the same database finds its rows."""
    name = f"contract_{next(_databases)}"
    first = ClickHouseStore(f"chdb://{chdb_dir}", database=name)
    first.migrate()
    first.append([ev.pose("r1", t0)])
    first.close()
    again = ClickHouseStore(f"chdb://{chdb_dir}", database=name)
    try:
        assert again.migrate() == SCHEMA_VERSION
        assert [r.robot_id for r in again.poses(t0, t0 + 1)] == ["r1"]
    finally:
        again.close()
    assert os.path.isdir(chdb_dir)


def test_clickhouse_reads_do_not_wait_for_a_writer(chdb_dir, ev, t0) -> None:
    """While a writer holds the write client (a long insert), reads still answer: they
    have a client of their own."""
    import threading

    store = _clickhouse(chdb_dir)
    try:
        store.migrate()
        store.append([ev.pose("r1", t0), ev.chunk("r1", t0, 0, 0)])
        answers: list = []
        with store._lock:  # what an insert holds for its whole duration
            reader = threading.Thread(target=lambda: answers.append(
                (len(store.poses(t0, t0 + 1)), len(store.map_at(t0)), len(store.robots_at(t0)))))
            reader.start()
            reader.join(60)
            assert answers == [(1, 1, 1)], "a read waited for the write lock"
    finally:
        store.close()


def test_schema_v6_compresses_quaternions_with_fpc(chdb_dir, ev, t0) -> None:
    """After migrate, the pose quaternion columns use FPC + ZSTD and still read back exactly."""
    store = _clickhouse(chdb_dir)
    try:
        store.migrate()
        codecs = dict(store.client.query(
            "SELECT name, compression_codec FROM system.columns WHERE database = {d:String} "
            "AND table = 'poses' AND name IN ('qx', 'qy', 'qz', 'qw')",
            parameters={"d": store.database}).result_rows)
        assert codecs == dict.fromkeys(("qx", "qy", "qz", "qw"), "CODEC(FPC(20), ZSTD(3))")
        store.append([make_envelope("r1", t0, t0, PoseReported(
            position=(1.0, 2.0, 0.0), orientation=(0.0, 0.0, 0.38268343, 0.92387953),
            battery_level=None))])
        (pose,) = store.poses(t0, t0 + 1)
        assert (pose.qx, pose.qy, pose.qz, pose.qw) == pytest.approx((0.0, 0.0, 0.38268343, 0.92387953), rel=1e-7)
    finally:
        store.close()


def test_schema_v5_keeps_the_latest_a_of_each_v3_conflict_and_reruns_safely(chdb_dir, t0) -> None:
    """A v4 database's pair-per-row conflicts become one row per B naming the latest A
    (ties in time: the greater robot); re-running v5 after it completed changes nothing."""
    from mapservice.core.ports import ConflictRow
    from mapservice.adapters.clickhouse.schema import migrations

    store = _clickhouse(chdb_dir)
    db, c = store.database, store.client
    try:
        c.command(f"CREATE DATABASE IF NOT EXISTS {db}")
        steps = migrations(db, store.retention_days)
        for m in steps[:4]:
            for statement in m.statements:
                c.command(statement)
        c.command(f"CREATE TABLE {db}.schema_migrations (version UInt32, description String, "
                  "applied DateTime DEFAULT now()) ENGINE = ReplacingMergeTree ORDER BY version")
        c.insert(f"{db}.schema_migrations", [[m.version, m.description] for m in steps[:4]],
                 column_names=["version", "description"])
        h = bytes(16)
        c.insert(f"{db}.conflicts", [
            [t0 + 5000, 1, 2, "a", t0 + 1000, h, "d", h], [t0 + 5000, 1, 2, "b", t0 + 3000, h, "d", h],
            [t0 + 5000, 1, 2, "c", t0 + 3000, h, "d", h], [t0 + 6000, 0, 0, "a", t0 + 10, h, "b", h]],
            column_names=["ts", "row", "col", "robot_a", "ts_a", "hash_a", "robot_b", "hash_b"])
        assert store.migrate() == SCHEMA_VERSION
        expected = [ConflictRow(1, 2, t0 + 5000, "c", t0 + 3000, "d"),
                    ConflictRow(0, 0, t0 + 6000, "a", t0 + 10, "b")]
        assert store.conflicts(t0, t0 + 10_000) == expected
        for statement in steps[4].statements:
            c.command(statement)
        assert store.conflicts(t0, t0 + 10_000) == expected
    finally:
        store.close()


# --- the 2019 REST contract: list_chunks, list_poses, delete_* ----------------------------



def _legacy_history(ev, t0):
    """Chunk writes and poses spread over two days, with ties in time, row and robot."""
    day = 86_400_000
    return [
        ev.chunk("r1", t0, 0, 0), ev.chunk("r2", t0, 0, 0), ev.chunk("r1", t0 + 1000, 0, 1),
        ev.chunk("r2", t0 + 2000, 1, 0, bytes([1]) * 10_000), ev.chunk("r1", t0 - 2 * 3_600_000, 1, 1),
        ev.chunk("r3", t0 - day - 5, 2, 0), ev.chunk("r1", t0 + 3000, 0, 0),
        ev.pose("r1", t0), ev.pose("r2", t0), ev.pose("r1", t0 + 1000), ev.pose("r2", t0 + 2000),
        ev.pose("r3", t0 - 2 * 3_600_000), ev.pose("r3", t0 - day - 5), ev.pose("r1", t0 + 3000),
    ]


def _chunk_keys(rows, t0):
    return [(r.ts_ms - t0, r.row, r.column, r.robot_id) for r in rows]


def test_list_chunks_default_is_newest_first_ten(store, ev, t0) -> None:
    """No parameters: the ten newest writes, newest first, ties by row, column, robot."""
    store.append(_legacy_history(ev, t0))
    rows = store.list_chunks(parse_chunk_query({}))
    assert _chunk_keys(rows, t0)[:5] == [(3000, 0, 0, "r1"), (2000, 1, 0, "r2"),
                                          (1000, 0, 1, "r1"), (0, 0, 0, "r1"), (0, 0, 0, "r2")]
    assert len(rows) == 7 and rows[0].content_hash == content_hash(bytes(10_000)).hex()


def test_list_chunks_filters(store, ev, t0) -> None:
    """row, column, robotId, timestamp, updatedSince (inclusive), updatedBefore (exclusive)."""
    store.append(_legacy_history(ev, t0))

    def keys(**params):
        return _chunk_keys(store.list_chunks(parse_chunk_query(
            {k: str(v) for k, v in params.items()})), t0)

    assert keys(row=1) == [(2000, 1, 0, "r2"), (-7_200_000, 1, 1, "r1")]
    assert keys(column=1) == [(1000, 0, 1, "r1"), (-7_200_000, 1, 1, "r1")]
    assert keys(row=0, column=0, robotId="r2") == [(0, 0, 0, "r2")]
    assert keys(timestamp=t0) == [(0, 0, 0, "r1"), (0, 0, 0, "r2")]
    assert keys(updatedSince=t0 + 1000) == [(3000, 0, 0, "r1"), (2000, 1, 0, "r2"),
                                            (1000, 0, 1, "r1")]
    assert keys(updatedSince=t0, updatedBefore=t0 + 1000) == [(0, 0, 0, "r1"), (0, 0, 0, "r2")]


def test_list_chunks_sort_skip_limit(store, ev, t0) -> None:
    """sort orders by the whitelisted fields; skip and limit page through the result."""
    store.append(_legacy_history(ev, t0))

    def keys(**params):
        return _chunk_keys(store.list_chunks(parse_chunk_query(params)), t0)

    assert keys(sort="timestamp:asc", limit="2") == [(-86_400_005, 2, 0, "r3"),
                                                     (-7_200_000, 1, 1, "r1")]
    assert keys(sort="row:desc,column:asc", limit="3") == [(-86_400_005, 2, 0, "r3"),
                                                            (2000, 1, 0, "r2"),
                                                            (-7_200_000, 1, 1, "r1")]
    assert keys(sort="robotId:desc", limit="1") == [(-86_400_005, 2, 0, "r3")]
    assert keys(skip="1", limit="2") == [(2000, 1, 0, "r2"), (1000, 0, 1, "r1")]
    assert keys(limit="0") == []


def test_list_poses_filters_sort_and_page(store, ev, t0) -> None:
    """robotId, timestamp, updatedSince/Before, sort, skip and limit on poses."""
    store.append(_legacy_history(ev, t0))

    def keys(**params):
        rows = store.list_poses(parse_pose_query({k: str(v) for k, v in params.items()}))
        return [(r.ts_ms - t0, r.robot_id) for r in rows]

    assert keys() == [(3000, "r1"), (2000, "r2"), (1000, "r1"), (0, "r1"), (0, "r2"),
                      (-7_200_000, "r3"), (-86_400_005, "r3")]
    assert keys(robotId="r3") == [(-7_200_000, "r3"), (-86_400_005, "r3")]
    assert keys(timestamp=t0) == [(0, "r1"), (0, "r2")]
    assert keys(updatedSince=t0 + 1000, updatedBefore=t0 + 3000) == [(2000, "r2"), (1000, "r1")]
    assert keys(sort="robotId:desc,timestamp:asc", limit=3) == [
        (-86_400_005, "r3"), (-7_200_000, "r3"), (0, "r2")]
    assert keys(skip=5, limit=5) == [(-7_200_000, "r3"), (-86_400_005, "r3")]


@pytest.mark.parametrize("params", [
    {}, {"limit": "1"}, {"limit": "3", "skip": "2"}, {"sort": "timestamp:asc"},
    {"updatedBefore": "T+1500"}, {"updatedBefore": "T+1500", "limit": "4"},
    {"sort": "column:desc,row:asc,timestamp:asc"}, {"robotId": "r1", "sort": "row:asc"},
    {"limit": "10000"},
])
def test_adapters_agree_on_legacy_queries(chdb_dir, ev, t0, params) -> None:
    """ClickHouse answers every 2019 query exactly as the in-memory fold does."""
    params = {k: str(t0 + int(v[2:])) if v.startswith("T+") else v for k, v in params.items()}
    memory, clickhouse = MemoryStore(), _clickhouse(chdb_dir)
    try:
        for s in (memory, clickhouse):
            s.migrate()
            s.append(_legacy_history(ev, t0))
        assert clickhouse.list_chunks(parse_chunk_query(params)) == \
            memory.list_chunks(parse_chunk_query(params))
        pose_params = {k: v for k, v in params.items() if "row" not in v and "column" not in v}
        assert clickhouse.list_poses(parse_pose_query(pose_params)) == \
            memory.list_poses(parse_pose_query(pose_params))
    finally:
        clickhouse.close()


def test_delete_chunks_empties_history_and_map(store, ev, t0) -> None:
    """delete_chunks removes every write, snapshot and conflict, keeps poses, counts what went."""
    from mapservice.core.ports import ConflictRow

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


# --- time-travel replay reads: timeline, robot_known, keyframe downsampling --------------


@pytest.fixture
def m0(t0) -> int:
    """A whole minute about an hour ago (keyframes are per minute)."""
    return t0 // 60_000 * 60_000


def test_timeline_counts_chunks_conflicts_and_robots(store, ev, m0) -> None:
    """timeline() gives every bucket, empty ones too, for whole-minute and odd buckets alike."""
    from mapservice.core.ports import ConflictRow, TimelineBucket

    store.append([ev.pose("r1", m0 + 1000), ev.pose("r2", m0 + 59_999), ev.pose("r1", m0 + 61_000),
                  ev.pose("r3", m0 + 179_000), ev.pose("r3", m0 + 181_000),
                  ev.chunk("r1", m0, 0, 0), ev.chunk("r2", m0 + 500, 0, 1),
                  ev.chunk("r1", m0 + 125_000, 0, 0), ev.chunk("r1", m0 + 180_000, 0, 0)])
    store.append([ev.pose("r1", m0 + 1000)])  # a duplicate counts once
    store.append_conflicts([ConflictRow(0, 1, m0 + 500, "r1", m0, "r2")])
    assert store.timeline(m0, m0 + 180_000, 3) == [
        TimelineBucket(m0, 2, 1, 2), TimelineBucket(m0 + 60_000, 0, 0, 1),
        TimelineBucket(m0 + 120_000, 1, 0, 1)]
    # 1,000 ms buckets starting off the minute: answered from every pose.
    assert store.timeline(m0 + 59_000, m0 + 62_000, 3) == [
        TimelineBucket(m0 + 59_000, 0, 0, 1), TimelineBucket(m0 + 60_000, 0, 0, 0),
        TimelineBucket(m0 + 61_000, 0, 0, 1)]
    assert store.timeline(m0, m0, 5) == []


def test_append_events_then_derive_views_reads_as_append(store, ev, m0) -> None:
    """The history consumer's two steps (store, push, then derive) leave the store as one append does."""
    batch = [ev.pose("r1", m0 + 1000), ev.pose("r2", m0 + 61_000), ev.pose("r1", m0 + 125_000),
             ev.chunk("r1", m0 + 500, 0, 0)]
    store.append_events(batch)
    assert store.poses(m0, m0 + 180_000) and store.chunk_events(m0, m0 + 180_000)  # queryable
    store.derive_views(batch)
    assert [(p.robot_id, p.ts_ms) for p in store.poses_downsampled(m0, m0 + 180_000, 60_000)] == [
        ("r1", m0 + 1000), ("r2", m0 + 61_000), ("r1", m0 + 125_000)]
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
    batches = [[ev.pose(f"r{int(rng.integers(0, 3))}", m0 + t, x=float(i % 7))
                for i, t in enumerate(times[k::4])] for k in range(4)]
    # Late: an earlier pose of a minute that already has a keyframe; and a rewrite.
    late = [ev.pose("r0", m0 + 120_000, x=42.0), ev.pose("r1", m0 + times[0], x=-1.0)]
    memory, clickhouse = MemoryStore(), _clickhouse(chdb_dir)
    try:
        for s in (memory, clickhouse):
            s.migrate()
            for batch in batches:
                s.append(batch)
            s.append(late)
        for f, t, step in [(m0, m0 + 600_000, 60_000), (m0, m0 + 600_000, 180_000),
                           (m0 + 60_000, m0 + 290_500, 120_000), (m0, m0 + 600_000, 600_000),
                           # off the minute, steps of >= 10 min: keyframes plus raw heads
                           (m0 + 12_345, m0 + 600_000, 600_000), (m0 - 7, m0 + 599_000, 650_001),
                           (m0 + 59_999, m0 + 600_000, 777_777)]:
            want = memory.poses_downsampled(f, t, step)
            assert clickhouse.poses_downsampled(f, t, step) == want
            assert (clickhouse.poses_downsampled(f, t, step, robot_id="r1")
                    == memory.poses_downsampled(f, t, step, robot_id="r1"))
        assert any(p.x == 42.0 for p in clickhouse.poses_downsampled(m0, m0 + 600_000, 60_000))
        assert clickhouse.timeline(m0, m0 + 600_000, 10) == memory.timeline(m0, m0 + 600_000, 10)
    finally:
        clickhouse.close()


def test_clickhouse_migration_v4_runs_twice_and_sorts_poses_by_time(chdb_dir, ev, t0) -> None:
    """Schema v4 re-sorts poses by (ts, robot_id) keeping every row; run again it changes
    nothing and the keyframe view still follows inserts."""
    store = _clickhouse(chdb_dir)
    try:
        store.migrate()
        store.append([ev.pose("r1", t0), ev.pose("r2", t0 + 1)])
        db, c = store.database, store.client
        c.command(f"DELETE FROM {db}.schema_migrations WHERE version = 4")
        assert store.migrate() == SCHEMA_VERSION
        (key,), = c.query("SELECT sorting_key FROM system.tables WHERE database = {d:String} "
                          "AND name = 'poses'", parameters={"d": db}).result_rows
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
    snapshot_rows = store.client.query(f"SELECT count() FROM {store.database}.map_snapshots").result_rows[0][0]
    late = base + 10 * 60_000 + 30_000  # between snapshot 1 and 2, later than everything there
    store.append([ev.chunk("late", late, 0, 0, bytes([200]) * 10_000),
                  ev.pose("r", late, x=99.0)])
    # Noted only: no snapshot row was written by the append.
    assert store.client.query(f"SELECT count() FROM {store.database}.map_snapshots").result_rows[0][0] == snapshot_rows
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
    assert store.client.query(f"SELECT count() FROM {store.database}.snapshot_repairs").result_rows[0][0] == 0
    (chunk,) = store.map_at(at)  # now from a repaired snapshot: still the late write
    assert (chunk.robot_id, chunk.ts_ms) == ("late", late)
    assert store.robots_at(at)[0].x == 99.0


# --- retention that keeps state (the long run: test_store_retention.py) ------------------

RET_T0 = 1_767_225_600_000  # 2026-01-01T00:00Z: long past, only the store's clock counts
DAY_MS = 86_400_000


def _retention_history(store, ev):
    """A floor written once (3 chunks), a pallet rewritten daily for ten days, a robot that
    reported once at the start and one that reports daily; the events, for the fold."""
    if hasattr(store, "snapshot_every_ms"):
        store.snapshot_every_ms = 6 * 3_600_000  # 40 snapshots for ten days, not 1,440
    written = [ev.chunk("mapper", RET_T0 + 1000, r, 0, bytes([r]) * 10_000) for r in range(3)]
    written += [ev.chunk("amr", RET_T0 + d * DAY_MS + 5000, 3, 3, bytes([50 + d]) * 10_000)
                for d in range(10)]
    store.append([ev.meta(RET_T0), *written, ev.pose("quiet", RET_T0 + 3_600_000),
                  *(ev.pose("busy", RET_T0 + d * DAY_MS + 7000) for d in range(10))])
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


# --- the change feed (rule: mapservice/core/change_feed.py) -------------------------------


def _feed(store, t0, **kw):
    from mapservice.core.change_feed import ChangeQuery
    return store.change_feed(ChangeQuery(kw.pop("f", t0), kw.pop("t", t0 + 3_600_000), **kw))


def _upload(ev, robot: str, t0: int, n: int = 25, cols: int = 10) -> list:
    """A floor upload: n chunks by one writer, 100 ms apart."""
    return [ev.chunk(robot, t0 + 100 * i, i // cols, i % cols, bytes([i]) * 10_000)
            for i in range(n)]


def test_change_feed_is_newest_first_with_previous_content(store, ev, t0) -> None:
    """Floor changes come newest first, each with the chunk's content before it (also from
    a write before the window); a map upload is one entry, never a floor change; a write
    that leaves a chunk as it was is none."""
    from mapservice.core.change_feed import UPLOAD_MIN_CHUNKS
    base = t0 - 1_200_000  # the upload: 20 minutes before the window's start
    store.append(_upload(ev, "uploader", base, UPLOAD_MIN_CHUNKS + 5))
    a, b, c = (bytes([200 + i]) * 10_000 for i in range(3))
    store.append([ev.chunk("r1", t0 + 60_000, 0, 1, a), ev.chunk("r2", t0 + 120_000, 0, 1, b),
                  ev.chunk("r1", t0 + 180_000, 2, 3, c),
                  # The same content again: no change of the floor.
                  ev.chunk("r3", t0 + 200_000, 0, 1, b), ev.chunk("r3", t0 + 201_000, 4, 4, bytes([44]) * 10_000)])
    entries = _feed(store, t0)
    assert [(e.kind, e.ts_ms - t0, e.row, e.column, e.robot_id) for e in entries] == [
        ("change", 201_000, 4, 4, "r3"), ("change", 180_000, 2, 3, "r1"), ("change", 120_000, 0, 1, "r2"),
        ("change", 60_000, 0, 1, "r1")]
    assert entries[0].previous_hash is None
    assert entries[1].content_hash == content_hash(c).hex()
    assert entries[1].previous_hash == content_hash(bytes([23]) * 10_000).hex()
    assert entries[2].previous_hash == content_hash(a).hex()
    assert entries[3].previous_hash == content_hash(bytes([1]) * 10_000).hex()
    uploads = _feed(store, t0, f=base)
    assert [(e.kind, e.robot_id, e.chunks, e.ts_ms - base, e.end_ms - base) for e in uploads
            if e.kind == "upload"] == [("upload", "uploader", UPLOAD_MIN_CHUNKS + 5, 0,
                                        100 * (UPLOAD_MIN_CHUNKS + 4))]
    assert sum(e.kind == "change" for e in uploads) == 4


def test_change_feed_filters_area_and_robot_and_pages(store, ev, t0) -> None:
    """A chunk box, a robot and a cursor narrow the feed; pages follow one another without
    gaps or repeats; a short burst (fewer writes than an upload) stays floor changes."""
    from mapservice.core.change_feed import ChangeCursor, ChunkBox
    store.append([ev.chunk(f"r{i % 3}", t0 + 1000 * i, i % 4, i % 5, bytes([i]) * 10_000)
                  for i in range(12)])
    everything = _feed(store, t0)
    assert len(everything) == 12 and all(e.kind == "change" for e in everything)
    box = ChunkBox(0, 1, 0, 1)
    assert [(e.row, e.column) for e in _feed(store, t0, box=box)] == [
        (r, c) for r, c in ((e.row, e.column) for e in everything) if r <= 1 and c <= 1]
    assert {e.robot_id for e in _feed(store, t0, robot_id="r1")} == {"r1"}
    assert len(_feed(store, t0, robot_id="r1")) == 4
    first = _feed(store, t0, limit=5)
    cursor = ChangeCursor(*first[-1].key())
    assert ChangeCursor.decode(cursor.encode()) == cursor
    second = _feed(store, t0, limit=5, before=cursor)
    third = _feed(store, t0, limit=5, before=ChangeCursor(*second[-1].key()))
    assert first + second + third == everything
    assert _feed(store, t0, f=t0 + 12_000) == []


def test_change_feed_upload_shows_in_an_area_it_touched(store, ev, t0) -> None:
    """An upload is listed for an area when any of its writes is in it, once."""
    from mapservice.core.change_feed import ChunkBox
    store.append(_upload(ev, "up", t0 + 1000, 30, cols=10))  # rows 0-2, columns 0-9
    assert [(e.kind, e.chunks) for e in _feed(store, t0, box=ChunkBox(2, 2, 5, 5))] == [("upload", 30)]
    assert _feed(store, t0, box=ChunkBox(5, 6, 0, 9)) == []


def test_change_feed_lists_one_kind_when_asked(store, ev, t0) -> None:
    """kind="upload" lists the uploads alone (the timeline's marks), kind="change" the floor
    changes alone; paging works within a kind."""
    from mapservice.core.change_feed import ChangeCursor
    store.append(_upload(ev, "up-a", t0 + 1000, 25) + _upload(ev, "up-b", t0 + 600_000, 22))
    store.append([ev.chunk("r1", t0 + 300_000 + 1000 * i, 7, i, bytes([90 + i]) * 10_000) for i in range(3)])
    assert [(e.kind, e.robot_id, e.chunks) for e in _feed(store, t0, kind="upload")] == [
        ("upload", "up-b", 22), ("upload", "up-a", 25)]
    assert [(e.kind, e.column) for e in _feed(store, t0, kind="change")] == [("change", 2), ("change", 1), ("change", 0)]
    first = _feed(store, t0, kind="upload", limit=1)
    assert [e.robot_id for e in _feed(store, t0, kind="upload", before=ChangeCursor(*first[0].key()))] == ["up-a"]


def test_change_feed_refuses_a_window_with_too_many_writes(store, ev, t0, monkeypatch) -> None:
    """More writes than the feed reads at once: WindowTooBusy, not minutes of work."""
    from mapservice.core import change_feed
    monkeypatch.setattr(change_feed, "MAX_WRITES", 5)
    store.append([ev.chunk("r1", t0 + 2000 * i, 0, i % 3, bytes([i]) * 10_000) for i in range(6)])
    with pytest.raises(change_feed.WindowTooBusy, match="shorter span"):
        _feed(store, t0)


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
    writes = [ev.chunk("map-upload", t0 - 10_000, 1, 2, grey), ev.chunk("a", t0, 1, 2, black),
              ev.chunk("b", t0 + 5_000, 1, 2, white)]
    store.append(writes)
    record_conflicts(store, store.chunk_writes_near([(1, 2)], t0 - 20_000, t0 + 20_000), 60_000)
    client = TestClient(create_app(Settings(), store, {}, ManualClock(t0 + 60_000)))
    body = client.get("/api/v1/conflicts", params={"from": t0 - 60_000, "to": t0 + 60_000}).json()
    assert body["conflicts"] == [{
        "row": 1, "column": 2, "ts_ms": t0 + 5_000, "robot_a": "a", "ts_a_ms": t0,
        "hash_a": content_hash(black).hex(), "robot_b": "b", "hash_b": content_hash(white).hex(),
        "seek_ms": t0 + 5_001}]
    assert store.conflicts(t0 - 60_000, t0 + 60_000) == [ConflictRow(1, 2, t0 + 5_000, "a", t0, "b")]
    at_seek = {(c.row, c.column): c.content_hash for c in store.map_at(t0 + 5_001)}
    assert at_seek[(1, 2)] == content_hash(white).hex()


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
    assert [(p.robot_id, p.ts_ms, p.x) for page in pages for p in page] == \
        [(p.robot_id, p.ts_ms, p.x) for p in whole]
    assert store.robots_at(at, after="b02", limit=2)[0].x == 7.0
    assert store.robots_at(at, after="zzz") == []
