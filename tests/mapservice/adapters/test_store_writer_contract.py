"""The store contract, writer and schema roles (`StoreSchema`, `HistoryWriter`, with
`StoreAdmin`'s counts): idempotent appends on each event's identity, what a stored pose,
chunk, map meta and dead letter keep.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py; shared helpers are in store_contract.py beside this module.
Times are taken from the wall clock (an hour ago, `t0`), because the ClickHouse tables drop
parts older than the retention.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.core.events import PoseReported, make_envelope
from mapservice.core.ports import Counts, PoseRow
from mapservice.core.wire2019 import content_hash
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import clone_migrated
from tests.mapservice.adapters.store_contract import clickhouse_store, random_pixels

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
    batch = [ev.pose("r1", t0), ev.pose("r2", t0), ev.chunk("r1", t0, 1, 1), ev.meta(t0)]
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
    store.append(
        [
            ev.chunk("r1", t0, 0, 0),
            ev.chunk("r2", t0, 0, 0),
            ev.chunk("r1", t0, 0, 1),
            ev.chunk("r1", t0, 1, 0),
        ]
    )
    assert store.counts().chunk_events == 4


def test_empty_appends_are_harmless(store) -> None:
    """Empty batches change nothing."""
    store.append([])
    store.append_dead_letters([])
    assert store.counts() == Counts(0, 0, 0, 0)


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
    store.append(
        [
            ev.chunk("r1", t0, 0, 0, random_pixels(5)),
            ev.chunk("r1", t0, 0, 1, random_pixels(6)),
            ev.chunk("r1", t0, 0, 2, random_pixels(5)),
        ]
    )
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
        robot_id="r1",
        ts_ms=t0,
        x=1.235,
        y=-2.0,
        z=0.001,
        qx=f32(0.1),
        qy=f32(-0.2),
        qz=f32(0.30000001),
        qw=f32(0.9273618),
        battery_level=f32(33.3),
        charging=True,
        loaded="dfs",
        path=((1.0, 2.001), (-0.5, 0.0)),
        receive_time_ms=t0 + 70,
    )


def test_receive_time_before_event_time_is_kept(store, ev, t0) -> None:
    """A robot clock slightly ahead (negative lag) keeps its exact receive time."""
    store.append(
        [ev.pose("r1", t0, receive_lag_ms=-250_000), ev.chunk("r1", t0, receive_lag_ms=-1)]
    )
    assert store.poses(t0, t0 + 1)[0].receive_time_ms == t0 - 250_000
    assert store.chunk_events(t0, t0 + 1)[0].receive_time_ms == t0 - 1


@pytest.mark.parametrize(
    "charging,loaded",
    [
        (True, False),
        (False, True),
        ("sdf", "dfs"),
        ("true", "false"),
        ("", "0"),
        (None, None),
        (True, None),
    ],
    ids=repr,
)
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
    events = [
        make_envelope("r1", t0, t0 + 70, PRECISE),
        make_envelope(
            "r2",
            t0 + 1,
            t0 + 2,
            PoseReported(
                position=(-123.4567, 0.0005, 10.0),
                orientation=(0.0, 0.0, 0.70710678, 0.70710678),
                battery_level=None,
                charging="sdf",
                loaded=False,
                path=None,
            ),
        ),
        ev.pose("r3", t0 + 2, x=0.0015, y=-0.0015),
        ev.chunk("r1", t0 + 3, 2, 3, random_pixels(7)),
        ev.chunk("r2", t0 + 3, 2, 3, random_pixels(7)),
        ev.meta(t0 + 4),
    ]
    memory, clickhouse = MemoryStore(), clickhouse_store(chdb_dir)
    clone_migrated(chdb_dir, clickhouse.database)
    try:
        for s in (memory, clickhouse):
            s.migrate()
            s.append(events)
        assert clickhouse.poses(t0, t0 + 10) == memory.poses(t0, t0 + 10)
        assert clickhouse.chunk_events(t0, t0 + 10) == memory.chunk_events(t0, t0 + 10)
        h = content_hash(random_pixels(7))
        assert clickhouse.chunk_content(h) == memory.chunk_content(h)
        assert clickhouse.latest_meta() == memory.latest_meta()
        assert clickhouse.counts() == memory.counts()
    finally:
        clickhouse.close()
