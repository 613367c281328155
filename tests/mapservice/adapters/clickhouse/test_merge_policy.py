"""The merge policy: every MergeTree table of a migrated store has it (a table a later
migration adds too), and under a quiet plant's stream of small inserts the day's big part
is left alone while the active parts stay bounded."""

from __future__ import annotations

import time

from mapservice.adapters.clickhouse.merge_policy import (
    MERGE_POLICY,
    apply_merge_policy,
    set_on_every_merge_tree_table,
)
from tests.mapservice.adapters.store_contract import clickhouse_store

DAY_MS = 86_400_000
T0_MS = 1_780_000_000_000 - 1_780_000_000_000 % DAY_MS
ROBOTS = 20


def merge_tree_tables(store) -> dict[str, str]:
    return dict(
        store.client.query(
            f"SELECT name, engine_full FROM system.tables WHERE database = '{store.database}' "
            "AND engine LIKE '%MergeTree'"
        ).result_rows
    )


def policy_missing(engine_full: str) -> list[str]:
    return [f"{n} = {v}" for n, v in MERGE_POLICY.items() if f"{n} = {v}" not in engine_full]


def test_every_merge_tree_table_has_the_policy_and_a_later_table_gets_it(chdb_dir) -> None:
    store = clickhouse_store(chdb_dir)
    try:
        store.migrate()
        tables = merge_tree_tables(store)
        assert len(tables) > 10  # the schema's tables, not an empty database
        assert {t: policy_missing(full) for t, full in tables.items() if policy_missing(full)} == {}

        # A table a later migration adds gets it at the next migrate; once set, nothing
        # is altered again.
        db = store.database
        store.client.command(
            f"CREATE TABLE {db}.added_later (k UInt32) ENGINE = ReplacingMergeTree ORDER BY k"
        )
        store.migrate()
        assert policy_missing(merge_tree_tables(store)["added_later"]) == []
        statements: list[str] = []
        rows = lambda sql: store.client.query(sql).result_rows  # noqa: E731
        assert apply_merge_policy(db, statements.append, rows) == []
        assert statements == []
    finally:
        store.close()


def test_a_changed_value_is_set_again_and_an_unknown_setting_left_out() -> None:
    """A policy whose value changed reaches the tables that have the old one; a setting the
    engine does not know (an older server) is not sent."""
    engine_full = "ReplacingMergeTree ORDER BY k SETTINGS index_granularity = 8192, a_b = 2"

    def rows(sql: str) -> list[tuple]:
        if "merge_tree_settings" in sql:
            return [("a_b",), ("c",)]
        return [("t1", engine_full), ("t2", engine_full.replace("a_b = 2", "a_b = 20"))]

    statements: list[str] = []
    changed = set_on_every_merge_tree_table(
        "db", {"a_b": 20, "unknown": 1}, statements.append, rows
    )
    assert changed == ["t1"]
    assert statements == ["ALTER TABLE db.t1 MODIFY SETTING a_b = 20"]


def poses_sql(db: str, rows: int, first_row: int) -> str:
    """`rows` poses of ROBOTS robots, a pose a second each, from the day's `first_row`."""
    return (
        f"INSERT INTO {db}.poses (robot_id, ts, x_mm, y_mm) SELECT "
        f"concat('robot-', toString(number % {ROBOTS})), "
        f"fromUnixTimestamp64Milli(toInt64({T0_MS} + intDiv(number, {ROBOTS}) * 1000 "
        f"+ number % {ROBOTS})), "
        f"toInt32(10000 + 5000 * sin(intDiv(number, {ROBOTS}) / 60 + number % {ROBOTS})), "
        f"toInt32(10000 + 5000 * cos(intDiv(number, {ROBOTS}) / 60 + number % {ROBOTS})) "
        f"FROM numbers({first_row}, {rows})"
    )


def rows_merged(store, table: str) -> int:
    """Rows of the table's parts a merge has replaced (kept on disk for
    `old_parts_lifetime`, 480 s, longer than this test)."""
    ((merged,),) = store.client.query(
        f"SELECT sum(rows) FROM system.parts WHERE database = '{store.database}' "
        f"AND table = '{table}' AND NOT active"
    ).result_rows
    return int(merged)


def test_small_inserts_merge_among_themselves_and_parts_stay_bounded(chdb_dir) -> None:
    """A day's partition holding two hours of 20 robots (about a MiB), then 240 inserts
    of four poses, as a quiet plant stores them: the engine's default merges the whole
    partition with every few new parts (about 40 times its rows over the run); under the
    policy the new parts merge among themselves, and the partition's active parts stay
    under 50 (where the selector's base has come down to 1), far from the engine's insert
    limits (1000, 3000)."""
    store = clickhouse_store(chdb_dir)
    try:
        store.migrate()
        db, c = store.database, store.client
        day_rows = 2 * 3600 * ROBOTS
        c.command(poses_sql(db, day_rows, 0))
        c.command(f"OPTIMIZE TABLE {db}.poses FINAL")
        before = rows_merged(store, "poses")
        inserts, most_parts = 240, 0
        for i in range(inserts):
            c.command(poses_sql(db, 4, day_rows + 4 * i))
            time.sleep(0.02)
            if i % 20 == 0:
                ((parts,),) = c.query(
                    f"SELECT count() FROM system.parts WHERE database = '{db}' "
                    "AND table = 'poses' AND active"
                ).result_rows
                most_parts = max(most_parts, int(parts))
        time.sleep(1.0)  # merges assigned by the last inserts
        merged = rows_merged(store, "poses") - before
        assert merged < 2 * day_rows, (merged, day_rows)
        assert most_parts < 50, most_parts
        ((stored,),) = c.query(f"SELECT count() FROM {db}.poses FINAL").result_rows
        assert stored == day_rows + 4 * inserts
    finally:
        store.close()
