"""A part a full disk cut short: chDB commits a part (an insert's, a merge's) whose files
the disk refused, and every read of it fails from then on. The store sets the part aside
and restores what it covered, so the writer's retry succeeds with nothing lost.

The disk's cut is made here by emptying files of a merged part of `poses` (what a filled
tmpfs left: files of size 0 under a committed part), one class of file at a time and all
at once.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from mapservice.adapters.clickhouse.broken_parts import (
    BROKEN_PART_CODES,
    RELOAD_COOLDOWN_S,
    BrokenPartRecovery,
    tables_named,
)
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.runtime.insert_health import code_of
from tests.conftest import clone_migrated
from tests.mapservice.adapters.store_contract import clickhouse_store

ROBOTS = ("r1", "r2", "r3")
BATCHES = 4  # each its own part, merged into one by OPTIMIZE


def batches(ev, t0: int) -> list[list]:
    return [
        [ev.pose(robot, t0 + b * 1000 + i * 100, x=i, y=b) for robot in ROBOTS for i in range(10)]
        for b in range(BATCHES)
    ]


def merged_poses_part(store: ClickHouseStore) -> Path:
    """The one active part of `poses` after merging the batches' parts; its directory."""
    db = store.database
    store.client.command(f"OPTIMIZE TABLE {db}.poses FINAL")
    ((name, path, level),) = store.client.query(
        f"SELECT name, path, level FROM system.parts WHERE database = '{db}' "
        "AND table = 'poses' AND active"
    ).result_rows
    assert level > 0 and name.split("_")[1] != name.split("_")[2], name  # a merge's output
    return Path(path)


def cut_short(part: Path, which: str) -> list[str]:
    """Empties the part's files of one kind (or all of them), as ENOSPC left them."""
    kinds = {
        "marks": lambda f: ".cmrk" in f.name or f.suffix in {".mrk", ".mrk2", ".mrk3"},
        "column data": lambda f: f.suffix == ".bin",
        "every file": lambda f: True,
    }
    files = [f for f in part.iterdir() if f.is_file() and kinds[which](f)]
    assert files, f"no {which} file in {sorted(p.name for p in part.iterdir())}"
    for f in files:
        f.write_bytes(b"")
    return [f.name for f in files]


@contextmanager
def store_with_a_cut_part(chdb_dir, ev, t0, which: str) -> Iterator[tuple]:
    """A migrated chDB store holding the batches' poses, its merged poses part cut short
    (`which` files emptied); yields the store, the batches sent and what was cut."""
    store = clickhouse_store(chdb_dir)
    clone_migrated(chdb_dir, store.database)
    try:
        store.migrate()
        sent = batches(ev, t0)
        for batch in sent:
            store.append_events(batch)
        yield store, sent, cut_short(merged_poses_part(store), which)
    finally:
        store.close()


# The primary index is not among them: the engine keeps a part's index from its writing,
# so emptying it on disk changes nothing until the next load.
@pytest.mark.parametrize("which", ["marks", "column data", "every file"])
def test_a_merged_part_cut_short_is_set_aside_and_its_sources_restored(
    chdb_dir, ev, t0, which
) -> None:
    """The derived views' re-read of the stored poses fails on the cut part once (the
    failure the writer records and retries); the retry succeeds, every pose is stored
    once, the part is in detached/ as broken-on-start."""
    with store_with_a_cut_part(chdb_dir, ev, t0, which) as (store, sent, cut):
        every = [e for batch in sent for e in batch]

        with pytest.raises(Exception) as failed:
            store.derive_views(every)
        assert code_of(failed.value) in BROKEN_PART_CODES, (cut, failed.value)

        store.derive_views(every)  # the writer's retry
        db = store.database
        keys = store.client.query(
            f"SELECT robot_id, toUnixTimestamp64Milli(ts) FROM {db}.poses FINAL"
        ).result_rows
        assert sorted(keys) == sorted((e.robot_id, e.event_time_ms) for e in every)
        assert len(store.poses(t0, t0 + BATCHES * 1000, limit=10_000)) == len(every)
        (derived,) = store.client.query(f"SELECT count() FROM {db}.pose_tracks FINAL").result_rows[
            0
        ]
        assert derived == len(every)
        detached = store.client.query(
            f"SELECT name FROM system.detached_parts WHERE database = '{db}' AND table = 'poses'"
        ).result_rows
        assert [n for (n,) in detached if n.startswith("broken")], detached


@pytest.mark.parametrize("which", ["marks", "every file"])
def test_a_read_that_meets_a_cut_short_part_recovers_it_too(chdb_dir, ev, t0, which) -> None:
    """The API's reads fail on the part once; the next read answers every pose (a part
    no insert re-reads would otherwise fail every read of its time range)."""
    with store_with_a_cut_part(chdb_dir, ev, t0, which) as (store, sent, _cut):
        window = (t0, t0 + BATCHES * 1000)
        with pytest.raises(Exception) as failed:
            store.poses(*window, limit=10_000)
        assert code_of(failed.value) in BROKEN_PART_CODES, failed.value
        got = store.poses(*window, limit=10_000)
        assert sorted((p.robot_id, p.ts_ms) for p in got) == sorted(
            (e.robot_id, e.event_time_ms) for batch in sent for e in batch
        )


def test_chdb_tables_keep_a_merges_sources_for_minutes(chdb_dir) -> None:
    """chDB's default removes a merge's sources at once; every MergeTree table of a
    migrated store keeps them 480 s, the time to restore them from a broken merged part."""
    store = clickhouse_store(chdb_dir)
    try:
        store.migrate()
        rows = store.client.query(
            f"SELECT name, engine_full FROM system.tables WHERE database = '{store.database}' "
            "AND engine LIKE '%MergeTree'"
        ).result_rows
        assert rows
        assert [n for n, full in rows if "old_parts_lifetime = 480" not in full] == []
    finally:
        store.close()


# --- the recovery's decisions, without an engine -------------------------------------------


class Engine:
    """Records statements; answers the lookups as an engine with `tables` would."""

    def __init__(self, tables: dict[str, str]) -> None:
        self.tables = tables  # name -> uuid
        self.statements: list[str] = []
        self.fail_attach = 0

    def command(self, sql: str) -> None:
        self.statements.append(sql)
        if sql.startswith("ATTACH") and self.fail_attach:
            self.fail_attach -= 1
            raise RuntimeError("Code: 1000. DB::Exception: busy. (LOGICAL_ERROR)")

    def rows(self, sql: str) -> list[tuple]:
        if "uuid = toUUID('" in sql:
            uuid = sql.split("toUUID('")[1].split("'")[0]
            return [(n,) for n, u in self.tables.items() if u == uuid]
        if "system.tables" in sql:
            return [(n,) for n in self.tables]
        if "system.detached_parts" in sql:
            return []
        raise AssertionError(f"unexpected query: {sql}")

    def reloaded(self) -> list[str]:
        return [s.split()[-1] for s in self.statements if s.startswith("DETACH")]


UUIDS = {
    "poses": "1b076b53-df2e-4040-9fb4-502a76a1fd79",
    "pose_tracks": "a54d30a4-99b4-4640-a0f4-445ac60f0f2f",
}


def recovery(engine: Engine, clock: list[float]) -> BrokenPartRecovery:
    return BrokenPartRecovery("db", engine.command, engine.rows, monotonic_s=lambda: clock[0])


@pytest.mark.parametrize(
    ("error", "expected"),
    [
        (
            "Code: 246. DB::Exception: Empty marks file '/x/store/1b0/"
            f"{UUIDS['poses']}/all_1_3_2/data.cmrk4': 0, must be: 112: (while reading from part "
            f"/x/store/1b0/{UUIDS['poses']}/all_1_3_2/ in table db.poses ({UUIDS['poses']})). "
            "(CORRUPTED_DATA)",
            ["db.poses"],
        ),
        (  # a part's path only
            f"Code: 33. DB::Exception: Cannot read all data: /d/store/a54/{UUIDS['pose_tracks']}"
            "/all_2_2_1/primary.cidx. (CANNOT_READ_ALL_DATA)",
            ["db.pose_tracks"],
        ),
        (  # no table named: every table that keeps parts
            "Code: 33. DB::Exception: Cannot read all data. Bytes read: 0. Bytes expected: 1. "
            "(CANNOT_READ_ALL_DATA)",
            ["db.pose_tracks", "db.poses"],
        ),
        ("Code: 243. DB::Exception: Cannot reserve 1.00 MiB. (NOT_ENOUGH_SPACE)", []),
        ("Code: 60. DB::Exception: Unknown table db.poses. (UNKNOWN_TABLE)", []),
        (  # another database's table
            "Code: 246. DB::Exception: Empty marks file (while reading from part /p/ in table "
            "other.poses (00000000-0000-0000-0000-000000000000)). (CORRUPTED_DATA)",
            ["db.pose_tracks", "db.poses"],
        ),
    ],
)
def test_which_tables_a_failure_reloads(error: str, expected: list[str]) -> None:
    engine = Engine(UUIDS)
    recovery(engine, [0.0]).after_failure(RuntimeError(error))
    assert engine.reloaded() == expected
    # Each detached table is attached again, right after.
    assert engine.statements == [
        stmt for t in expected for stmt in (f"DETACH TABLE {t}", f"ATTACH TABLE {t}")
    ]


def test_a_table_is_reloaded_again_only_after_the_cooldown() -> None:
    engine, clock = Engine(UUIDS), [100.0]
    recover = recovery(engine, clock)
    error = RuntimeError(f"in table db.poses ({UUIDS['poses']}). (CORRUPTED_DATA)")
    assert recover.after_failure(error) == ["poses"]
    clock[0] += RELOAD_COOLDOWN_S - 1
    assert recover.after_failure(error) == []
    clock[0] += 1
    assert recover.after_failure(error) == ["poses"]


def test_a_table_whose_attach_fails_is_attached_at_the_next_failure() -> None:
    engine = Engine(UUIDS)
    recover = recovery(engine, [0.0])
    engine.fail_attach = 5  # every try of this failure
    error = RuntimeError(f"in table db.poses ({UUIDS['poses']}). (CORRUPTED_DATA)")
    with pytest.raises(RuntimeError):
        recover.after_failure(error)
    engine.statements.clear()
    recover.after_failure(RuntimeError("(UNKNOWN_TABLE)"))
    assert engine.statements == ["ATTACH TABLE db.poses"]


def test_a_clickhouse_server_is_never_reloaded() -> None:
    """Over HTTP the failure is raised as it came and nothing is sent to the server (the
    address does not even answer)."""
    connection = ClickHouseConnection("http://127.0.0.1:9", timeout_s=1)
    error = RuntimeError("Empty marks file. (CORRUPTED_DATA)")
    with pytest.raises(RuntimeError) as raised, connection.reloading_broken_tables():
        raise error
    assert raised.value is error
    assert connection._broken_parts is None and connection._client is None


def test_the_names_in_an_error() -> None:
    error = f"while reading from part /a/store/1b0/{UUIDS['poses']}/p/ in table `db`.`poses` ("
    assert tables_named(error, "db", lambda u: None) == {"poses"}
    assert tables_named(error, "other", {UUIDS["poses"]: "poses"}.get) == {"poses"}
