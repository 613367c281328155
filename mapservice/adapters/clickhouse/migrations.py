"""The store's schema: its version, applying the numbered migrations of `schema` under a
lock table, checking their checksums, and breaking a lock a dead migrator left.

`ClickHouseSchema` (the StoreSchema role) runs on the writer client of the
`connection.ClickHouseConnection` it holds; it depends on that, on `schema` (the migrations)
and on `cluster` (ON CLUSTER DDL), never on the store's other roles.
"""

from __future__ import annotations

import os
import socket
import time
from typing import Any

import clickhouse_connect.driver.exceptions
import structlog

from mapservice.adapters.clickhouse.broken_parts import keep_merged_sources
from mapservice.adapters.clickhouse.cluster import for_cluster
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.adapters.clickhouse.merge_policy import apply_merge_policy
from mapservice.adapters.clickhouse.schema import checksums, migrations

log = structlog.get_logger(__name__)


MIGRATION_LOCK = "schema_migration_lock"


class MigrationLocked(RuntimeError):
    """Another migrator holds the lock past the timeout."""


class MigrationChanged(RuntimeError):
    """An applied migration's statements differ from this release's."""


class ClickHouseSchema:
    """Schema version, migrate, the migration lock."""

    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def schema_version(self) -> int:
        """The highest applied migration (0 on an empty database)."""
        try:
            ((version,),) = self.connection.rows(
                f"SELECT max(version) FROM {self.connection.database}.schema_migrations", {}
            )
        except Exception:  # no database or table yet
            return 0
        return int(version or 0)

    def migrate(self, lock_timeout_s: float = 600.0, holder: str | None = None) -> int:
        """Applies the migrations not applied yet, under a lock, and returns the version.

        The lock is a table that only one `CREATE TABLE` can create (ClickHouse refuses the
        second with TABLE_ALREADY_EXISTS): two migrators never interleave statements, the
        second waits and then finds everything applied. Each applied migration keeps a
        checksum of its statements; a migration edited after it ran is an error."""
        db = self.connection.database
        holder = holder or f"{socket.gethostname()}:{os.getpid()}"
        with self.connection.lock:
            c = self.connection.client
            ddl = self._ddl
            ddl(f"CREATE DATABASE IF NOT EXISTS {db}")
            ddl(
                f"CREATE TABLE IF NOT EXISTS {db}.schema_migrations (version UInt32, "
                "description String, applied DateTime DEFAULT now()) "
                "ENGINE = ReplacingMergeTree ORDER BY version"
            )
            ddl(
                f"ALTER TABLE {db}.schema_migrations ADD COLUMN IF NOT EXISTS "
                "checksum String DEFAULT ''"
            )
            self._take_migration_lock(holder, lock_timeout_s)
            try:
                applied = dict(
                    c.query(
                        f"SELECT version, checksum FROM {db}.schema_migrations FINAL"
                    ).result_rows
                )
                version = max(applied, default=0)
                released = checksums()
                for m in migrations(db, self.connection.retention_days):
                    if m.version in applied:
                        if applied[m.version] and applied[m.version] != released[m.version]:
                            raise MigrationChanged(
                                f"schema migration {m.version} ({m.description}) differs from the "
                                "one applied to this database; migrations must never change once "
                                "released: add a new one instead"
                            )
                        continue
                    log.info(
                        "applying schema migration", version=m.version, description=m.description
                    )
                    for statement in m.statements:
                        ddl(statement)
                    c.insert(
                        f"{db}.schema_migrations",
                        [[m.version, m.description, released[m.version]]],
                        column_names=["version", "description", "checksum"],
                    )
                    version = max(version, m.version)
            finally:
                ddl(f"DROP TABLE IF EXISTS {db}.{MIGRATION_LOCK} SYNC")
            self.connection.forget_insert_contexts()  # column types may have changed
            keep_merged_sources(db, ddl, self._rows)
            apply_merge_policy(db, ddl, self._rows)
            return version

    def _rows(self, sql: str) -> list[tuple[Any, ...]]:
        return list(self.connection.client.query(sql).result_rows)

    def _ddl(self, statement: str) -> None:
        """A schema statement, ON CLUSTER with Replicated engines where a cluster is set."""
        self.connection.client.command(for_cluster(statement, self.connection.cluster))

    def _take_migration_lock(self, holder: str, timeout_s: float) -> None:
        db, c = self.connection.database, self.connection.client
        deadline = time.monotonic() + timeout_s
        waited = False
        while True:
            try:
                # Log, not MergeTree: on a cluster each replica has its own lock table,
                # and ON CLUSTER DDL runs in one queue, so one CREATE still wins.
                self._ddl(
                    f"CREATE TABLE {db}.{MIGRATION_LOCK} (holder String, since DateTime "
                    "DEFAULT now()) ENGINE = Log"
                )
                c.insert(f"{db}.{MIGRATION_LOCK}", [[holder]], column_names=["holder"])
                return
            except clickhouse_connect.driver.exceptions.DatabaseError as exc:
                if (
                    "already exists" not in str(exc).lower()
                    and "(57)" not in str(exc)
                    and "code: 57" not in str(exc).lower()
                ):
                    raise
            try:
                rows = c.query(f"SELECT holder, since FROM {db}.{MIGRATION_LOCK}").result_rows
            except clickhouse_connect.driver.exceptions.DatabaseError as exc:
                if "unknown_table" in str(exc).lower() or "code: 60" in str(exc).lower():
                    continue  # released between our CREATE and this look: take it now
                raise
            who = f"{rows[0][0]} since {rows[0][1]} UTC" if rows else "another migrator"
            if time.monotonic() > deadline:
                raise MigrationLocked(
                    f"schema migrations are locked by {who}; if that process is gone, run "
                    f"`mapservice migrate --break-lock` (drops {db}.{MIGRATION_LOCK})"
                )
            if not waited:
                log.info("waiting for another schema migration", holder=who)
                waited = True
            time.sleep(0.5)

    def break_migration_lock(self) -> bool:
        """Drops a lock left by a migrator that died; True if there was one."""
        db = self.connection.database
        with self.connection.lock:
            existed = bool(
                self.connection.client.query(f"EXISTS TABLE {db}.{MIGRATION_LOCK}").result_rows[0][
                    0
                ]
            )
            self._ddl(f"DROP TABLE IF EXISTS {db}.{MIGRATION_LOCK} SYNC")
            return existed
