"""Recovering the embedded engine (chDB) from a part a full disk left broken.

When the disk fills while chDB writes a part (an insert's or a merge's), the engine can
commit the part with files the disk cut short: an empty marks file, an empty checksums
file. Every later read of that part fails (CORRUPTED_DATA "Empty marks file",
CANNOT_READ_ALL_DATA "Bytes read: 0"), and with it every insert that reads the table (the
derived views re-read the stored poses) and every merge, for as long as the process lives:
a non-replicated MergeTree never checks its parts again while the table is loaded.

ClickHouse's own remedy is loading the table again: on load it sets a part it cannot load
aside as `detached/broken-on-start_<part>` (kept for inspection, never deleted) and
activates the parts a broken merged part covers when they are still on disk, so the rows
come back from the merge's sources. Those are on disk only for `old_parts_lifetime` after
the merge, which chDB sets to 0 (a server: 480 s), so a merge a full disk cut short lost
its rows at once; `keep_merged_sources` gives the tables ClickHouse's usual 480 s.
`BrokenPartRecovery` reloads, DETACH TABLE then ATTACH TABLE, for the tables a failure names (every MergeTree table of the database when
it names none), after a failure whose code says a part could not be read. Only for chDB, whose data this process owns: a ClickHouse server is
restarted (or its part repaired) by its operator, and other clients may be using it.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterable
from typing import Any

import structlog

from mapservice.adapters.clickhouse.merge_policy import set_on_every_merge_tree_table
from mapservice.runtime.insert_health import code_of, describe

log = structlog.get_logger(__name__)

# Error codes of a part's files found shorter or other than its metadata says.
BROKEN_PART_CODES = frozenset(
    {
        "CORRUPTED_DATA",
        "CANNOT_READ_ALL_DATA",
        "ATTEMPT_TO_READ_AFTER_EOF",
        "CHECKSUM_DOESNT_MATCH",
        "BAD_SIZE_OF_FILE_IN_DATA_PART",
        "NO_FILE_IN_DATA_PART",
        "CANNOT_READ_FROM_FILE_DESCRIPTOR",
        "UNKNOWN_PART_TYPE",
    }
)
# ClickHouse names a part's table in a read's error ("in table db.name (uuid)") and its
# directory by the table's UUID (".../store/abc/<uuid>/<part>/").
_NAMED_TABLE = re.compile(r"in table `?(\w+)`?\.`?(\w+)`? \(")
_STORE_UUID = re.compile(
    r"/store/[0-9a-f]{3}/([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})/"
)
# After a reload that did not help, the same tables are not reloaded again before this:
# a read error that has another cause must not make every retry reload the tables.
RELOAD_COOLDOWN_S = 10.0
_ATTACH_TRIES = 5
# How long a merge's sources stay on disk (ClickHouse server's default).
MERGED_SOURCES_KEPT_S = 480


def keep_merged_sources(
    database: str,
    command: Callable[[str], object],
    query_rows: Callable[[str], Iterable[tuple[Any, ...]]],
) -> list[str]:
    """Sets `old_parts_lifetime` to MERGED_SOURCES_KEPT_S on the database's MergeTree
    tables where the engine's default is shorter (chDB's 0) and the table does not set it
    so already; returns them. Nothing to do on a ClickHouse server (its default is that already)."""
    ((default,),) = list(
        query_rows(
            "SELECT toUInt64OrZero(value) FROM system.merge_tree_settings "
            "WHERE name = 'old_parts_lifetime'"
        )
    )
    if int(default) >= MERGED_SOURCES_KEPT_S:
        return []
    tables = set_on_every_merge_tree_table(
        database, {"old_parts_lifetime": MERGED_SOURCES_KEPT_S}, command, query_rows
    )
    if tables:
        log.info(
            "merged parts' sources kept on disk for a while, to restore them should a full "
            "disk break the merged part",
            old_parts_lifetime_s=MERGED_SOURCES_KEPT_S,
            tables=tables,
        )
    return tables


def is_broken_part_error(exc: BaseException) -> bool:
    return code_of(exc) in BROKEN_PART_CODES


def tables_named(error: str, database: str, table_of_uuid: Callable[[str], str | None]) -> set[str]:
    """The tables of `database` whose parts `error` names: by name, or by the UUID in a
    part's path (`table_of_uuid` looks it up)."""
    named = {table for db, table in _NAMED_TABLE.findall(error) if db == database}
    for uuid in _STORE_UUID.findall(error):
        if (table := table_of_uuid(uuid)) is not None:
            named.add(table)
    return named


class BrokenPartRecovery:
    """Reloads the tables a broken-part failure names, at most once per RELOAD_COOLDOWN_S
    for the same tables. `command` runs one statement on the engine (the writer client)."""

    def __init__(
        self,
        database: str,
        command: Callable[[str], object],
        query_rows: Callable[[str], Iterable[tuple[Any, ...]]],
        monotonic_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.database = database
        self.command = command
        self.query_rows = query_rows
        self.monotonic_s = monotonic_s
        self._reloaded_at: dict[str, float] = {}
        self._to_attach: set[str] = set()  # detached by a reload whose ATTACH failed

    def _table_of_uuid(self, uuid: str) -> str | None:
        rows = list(
            self.query_rows(
                f"SELECT name FROM system.tables WHERE database = '{self.database}' "
                f"AND uuid = toUUID('{uuid}')"
            )
        )
        return rows[0][0] if rows else None

    def _part_tables(self) -> list[str]:
        """The database's tables that keep parts (the MergeTree family)."""
        return [
            name
            for (name,) in self.query_rows(
                f"SELECT name FROM system.tables WHERE database = '{self.database}' "
                "AND engine LIKE '%MergeTree'"
            )
        ]

    def after_failure(self, exc: BaseException) -> list[str]:
        """Reloads the tables `exc` names as holding a part that cannot be read (all
        that keep parts when it names none); returns them (none: not such a failure, or
        reloaded a moment ago)."""
        for table in sorted(self._to_attach):
            self._attach(table)
        if not is_broken_part_error(exc):
            return []
        now = self.monotonic_s()
        # An index or a checksums file read before any part is named (CANNOT_READ_ALL_DATA
        # "Bytes read: 0. Bytes expected: 1" alone) leaves every part-keeping table a suspect.
        named = tables_named(str(exc), self.database, self._table_of_uuid) or set(
            self._part_tables()
        )
        due = sorted(
            t
            for t in named
            if now - self._reloaded_at.get(t, -RELOAD_COOLDOWN_S) >= RELOAD_COOLDOWN_S
        )
        if not due:
            return []
        log.warning(
            "reloading tables after a part could not be read: ClickHouse sets a part it "
            "cannot load aside in detached/broken-on-start_* and restores what it covered",
            tables=due,
            reason=describe(exc),
        )
        before = self._set_aside()
        for table in due:
            self.command(f"DETACH TABLE {self.database}.{table}")
            self._to_attach.add(table)
            self._attach(table)
            self._reloaded_at[table] = self.monotonic_s()
        log.warning(
            "tables reloaded", tables=due, broken_parts_set_aside=sorted(self._set_aside() - before)
        )
        return due

    def _set_aside(self) -> set[str]:
        """The database's parts ClickHouse has set aside as broken ("table/part")."""
        return {
            f"{table}/{name}"
            for table, name in self.query_rows(
                f"SELECT table, name FROM system.detached_parts WHERE database = '{self.database}' "
                "AND startsWith(name, 'broken')"
            )
        }

    def _attach(self, table: str) -> None:
        """ATTACH TABLE, a few times; still failing, it stays to attach at the next call
        (the table is back at the latest when the process opens the engine again)."""
        qualified = f"{self.database}.{table}"
        for attempt in range(1, _ATTACH_TRIES + 1):
            try:
                self.command(f"ATTACH TABLE {qualified}")
            except Exception as exc:  # noqa: BLE001 - a detached table must come back
                if "already exists" in str(exc).lower():  # attached after all
                    break
                log.warning(
                    "attaching a reloaded table failed", table=qualified, error=describe(exc)
                )
                if attempt == _ATTACH_TRIES:
                    raise
                time.sleep(0.2 * attempt)
            else:
                break
        self._to_attach.discard(table)
