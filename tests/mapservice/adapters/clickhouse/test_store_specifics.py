"""ClickHouseStore on chDB only: what the store contract cannot see (contents written once
per hash and day, reopening, reads beside a writer, migrations' data).
"""

from __future__ import annotations

import os

import pytest

from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.core.events import PoseReported, make_envelope
from tests.conftest import clone_migrated
from tests.mapservice.adapters.store_contract import clickhouse_store, random_pixels

# --- ClickHouse specifics -----------------------------------------------------------------


def test_clickhouse_writes_content_once_per_hash_and_day(chdb_dir, ev, t0) -> None:
    """ClickHouse inserts a content's pixels once per day, not once per chunk write."""
    store = clickhouse_store(chdb_dir)
    clone_migrated(chdb_dir, store.database)
    try:
        store.migrate()
        pixels = random_pixels(8)
        for i in range(4):
            store.append([ev.chunk("r1", t0 + i, 0, i, pixels)])
        (physical,) = store.client.query(
            f"SELECT count() FROM {store.database}.chunk_contents"
        ).result_rows[0]
        assert physical == 1
    finally:
        store.close()


def test_clickhouse_store_reopens_with_its_data(chdb_dir, ev, t0) -> None:
    """A ClickHouseStore closed and opened again on the same database finds its rows."""
    name = f"reopen_{t0}"
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

    store = clickhouse_store(chdb_dir)
    clone_migrated(chdb_dir, store.database)
    try:
        store.migrate()
        store.append([ev.pose("r1", t0), ev.chunk("r1", t0, 0, 0)])
        answers: list = []
        with store.lock:  # what an insert holds for its whole duration
            reader = threading.Thread(
                target=lambda: answers.append(
                    (len(store.poses(t0, t0 + 1)), len(store.map_at(t0)), len(store.robots_at(t0)))
                )
            )
            reader.start()
            reader.join(60)
            assert answers == [(1, 1, 1)], "a read waited for the write lock"
    finally:
        store.close()


def test_schema_v6_compresses_quaternions_with_fpc(chdb_dir, ev, t0) -> None:
    """After migrate, the pose quaternion columns use FPC + ZSTD and still read back exactly."""
    store = clickhouse_store(chdb_dir)
    try:
        store.migrate()
        codecs = dict(
            store.client.query(
                "SELECT name, compression_codec FROM system.columns WHERE database = {d:String} "
                "AND table = 'poses' AND name IN ('qx', 'qy', 'qz', 'qw')",
                parameters={"d": store.database},
            ).result_rows
        )
        assert codecs == dict.fromkeys(("qx", "qy", "qz", "qw"), "CODEC(FPC(20), ZSTD(3))")
        store.append(
            [
                make_envelope(
                    "r1",
                    t0,
                    t0,
                    PoseReported(
                        position=(1.0, 2.0, 0.0),
                        orientation=(0.0, 0.0, 0.38268343, 0.92387953),
                        battery_level=None,
                    ),
                )
            ]
        )
        (pose,) = store.poses(t0, t0 + 1)
        assert (pose.qx, pose.qy, pose.qz, pose.qw) == pytest.approx(
            (0.0, 0.0, 0.38268343, 0.92387953), rel=1e-7
        )
    finally:
        store.close()


def test_schema_v5_keeps_the_latest_a_of_each_v3_conflict_and_reruns_safely(chdb_dir, t0) -> None:
    """A v4 database's pair-per-row conflicts become one row per B naming the latest A
    (ties in time: the greater robot); re-running v5 after it completed changes nothing."""
    from mapservice.adapters.clickhouse.schema import migrations
    from mapservice.core.ports import ConflictRow

    store = clickhouse_store(chdb_dir)
    db, c = store.database, store.client
    try:
        c.command(f"CREATE DATABASE IF NOT EXISTS {db}")
        steps = migrations(db, store.retention_days)
        for m in steps[:4]:
            for statement in m.statements:
                c.command(statement)
        c.command(
            f"CREATE TABLE {db}.schema_migrations (version UInt32, description String, "
            "applied DateTime DEFAULT now()) ENGINE = ReplacingMergeTree ORDER BY version"
        )
        c.insert(
            f"{db}.schema_migrations",
            [[m.version, m.description] for m in steps[:4]],
            column_names=["version", "description"],
        )
        h = bytes(16)
        c.insert(
            f"{db}.conflicts",
            [
                [t0 + 5000, 1, 2, "a", t0 + 1000, h, "d", h],
                [t0 + 5000, 1, 2, "b", t0 + 3000, h, "d", h],
                [t0 + 5000, 1, 2, "c", t0 + 3000, h, "d", h],
                [t0 + 6000, 0, 0, "a", t0 + 10, h, "b", h],
            ],
            column_names=["ts", "row", "col", "robot_a", "ts_a", "hash_a", "robot_b", "hash_b"],
        )
        assert store.migrate() == SCHEMA_VERSION
        expected = [
            ConflictRow(1, 2, t0 + 5000, "c", t0 + 3000, "d"),
            ConflictRow(0, 0, t0 + 6000, "a", t0 + 10, "b"),
        ]
        assert store.conflicts(t0, t0 + 10_000) == expected
        for statement in steps[4].statements:
            c.command(statement)
        assert store.conflicts(t0, t0 + 10_000) == expected
    finally:
        store.close()
