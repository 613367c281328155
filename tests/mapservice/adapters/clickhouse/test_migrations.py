"""Schema migrations: once each under a lock, checksums that catch an edited migration, and
a clear error while another migrator holds the lock."""

from __future__ import annotations

import threading
import time

import pytest

from mapservice.adapters.clickhouse.migrations import (
    MIGRATION_LOCK,
    MigrationChanged,
    MigrationLocked,
)
from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION, checksums
from mapservice.adapters.clickhouse.store import ClickHouseStore

_n = iter(range(1000))


@pytest.fixture
def store(chdb_dir):
    s = ClickHouseStore(f"chdb://{chdb_dir}", database=f"m{next(_n)}")
    yield s
    s.close()


def test_migrate_records_each_version_once_with_its_checksum(store) -> None:
    """Every migration is recorded once, with the released checksum; the lock is gone after."""
    assert store.schema_version() == 0
    assert store.migrate() == SCHEMA_VERSION == store.migrate()
    rows = store.client.query(
        f"SELECT version, checksum FROM {store.database}.schema_migrations"
    ).result_rows
    assert dict(rows) == checksums() and len(rows) == SCHEMA_VERSION
    assert not store.client.query(f"EXISTS TABLE {store.database}.{MIGRATION_LOCK}").result_rows[0][
        0
    ]


def test_checksums_ignore_the_settings_a_migration_ran_with(store) -> None:
    """Another database name or retention renders other text but the same checksums."""
    other = ClickHouseStore(store.dsn, database=store.database, retention_days=3)
    other.migrate()
    assert (
        ClickHouseStore(store.dsn, database=store.database, retention_days=7).migrate()
        == SCHEMA_VERSION
    )


def test_an_edited_migration_is_refused(store) -> None:
    """A recorded checksum that differs from this release's stops the migration, naming it."""
    store.migrate()
    store.client.command(
        f"ALTER TABLE {store.database}.schema_migrations UPDATE checksum = 'x' "
        "WHERE version = 3 SETTINGS mutations_sync = 1"
    )
    with pytest.raises(MigrationChanged, match="migration 3"):
        store.migrate()


def test_a_held_lock_makes_a_second_migrator_wait_then_fail_clearly(store) -> None:
    """While the lock is held another migrate waits; past its timeout it names the holder."""
    store.migrate()
    store.client.command(
        f"CREATE TABLE {store.database}.{MIGRATION_LOCK} (holder String, "
        "since DateTime DEFAULT now()) ENGINE = Log"
    )
    store.client.insert(f"{store.database}.{MIGRATION_LOCK}", [["job-7"]], column_names=["holder"])
    with pytest.raises(MigrationLocked, match=r"job-7.*--break-lock"):
        store.migrate(lock_timeout_s=1.0)
    assert store.break_migration_lock() is True
    assert store.migrate() == SCHEMA_VERSION


def test_a_lock_released_while_the_waiter_looks_at_it_is_taken(store) -> None:
    """The holder drops the lock between the waiter's failed CREATE and its look at the holder (seen in CI): the waiter takes the lock instead of failing."""
    store.migrate()
    db = store.database
    store.client.command(
        f"CREATE TABLE {db}.{MIGRATION_LOCK} (holder String, "
        "since DateTime DEFAULT now()) ENGINE = Log"
    )
    real_ddl, released = store._ddl, []

    def ddl(statement: str) -> None:
        try:
            real_ddl(statement)
        finally:
            if f"CREATE TABLE {db}.{MIGRATION_LOCK}" in statement and not released:
                released.append(True)  # the other migrator finishes right now
                store.client.command(f"DROP TABLE {db}.{MIGRATION_LOCK} SYNC")

    store._ddl = ddl
    assert store.migrate(lock_timeout_s=5) == SCHEMA_VERSION and released


def test_two_migrators_at_once_apply_each_migration_once(chdb_dir) -> None:
    """Two stores migrating one empty database at the same moment: one waits for the other."""
    database = f"m{next(_n)}"
    stores = [ClickHouseStore(f"chdb://{chdb_dir}", database=database) for _ in range(2)]
    results, errors = [], []

    def run(s):
        try:
            # Generous: the waiter's timeout is not under test, and a loaded CI machine took
            # over a minute for the first migrator's eight migrations.
            results.append(s.migrate(lock_timeout_s=300))
        except Exception as exc:  # noqa: BLE001 (reported below)
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(s,)) for s in stores]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(330)
        assert errors == [] and results == [SCHEMA_VERSION, SCHEMA_VERSION]
        versions = [
            v
            for (v,) in stores[0]
            .client.query(f"SELECT version FROM {database}.schema_migrations")
            .result_rows
        ]
        assert sorted(versions) == list(range(1, SCHEMA_VERSION + 1))
    finally:
        for s in stores:  # closed even on failure: a leaked chDB handle breaks later modules
            s.close()


def test_v10_moves_the_pose_views_behind_derive_views_and_keeps_what_v9_derived(
    store, monkeypatch
) -> None:
    """A v9 database keeps its keyframes through v10; after it, poses reach the views only through derive_views."""
    from mapservice.adapters.clickhouse import migrations as migrations_module
    from tests.conftest import pose_event

    released = migrations_module.migrations
    monkeypatch.setattr(
        migrations_module,
        "migrations",
        lambda db, days: [m for m in released(db, days) if m.version <= 9],
    )
    assert store.migrate() == 9
    hour_ago = int(time.time() * 1000) - 3_600_000  # inside the retention
    t0 = hour_ago - hour_ago % 60_000  # a whole minute
    store.append_events([pose_event("r1", t0 + s * 1000) for s in range(0, 120, 10)])

    def derived() -> tuple[int, int]:
        return tuple(
            store.client.query(f"SELECT count() FROM {store.database}.{t} FINAL").result_rows[0][0]
            for t in ("pose_keyframes", "pose_minutes")
        )

    assert derived() == (2, 2)  # v9: the views on poses fill them on insert
    monkeypatch.setattr(migrations_module, "migrations", released)
    assert store.migrate() == SCHEMA_VERSION
    assert derived() == (2, 2)
    later = [pose_event("r1", t0 + 120_000 + s * 1000) for s in range(0, 60, 10)]
    store.append_events(later)
    assert derived() == (2, 2)  # stored, not derived yet
    store.derive_views(later)
    store.derive_views(later)  # a re-delivered batch changes nothing
    assert derived() == (3, 3)


def test_v11_removes_every_ttl_and_keeps_the_rows(store, monkeypatch) -> None:
    """ClickHouse's TTL follows the real clock and dropped a floor written once; from v11
    on no table expires by itself (the service's retention step owns expiry)."""
    from mapservice.adapters.clickhouse import migrations as migrations_module
    from tests.conftest import chunk_event

    released = migrations_module.migrations
    monkeypatch.setattr(
        migrations_module,
        "migrations",
        lambda db, days: [m for m in released(db, days) if m.version <= 10],
    )
    assert store.migrate() == 10

    def with_ttl() -> list[str]:
        return [
            name
            for name, ddl in store.client.query(
                "SELECT name, create_table_query FROM system.tables WHERE database = {d:String}",
                parameters={"d": store.database},
            ).result_rows
            if " TTL " in ddl
        ]

    assert "chunk_events" in with_ttl()
    hour_ago = int(time.time() * 1000) - 3_600_000
    store.append_events([chunk_event("r1", hour_ago)])
    monkeypatch.setattr(migrations_module, "migrations", released)
    assert store.migrate() == SCHEMA_VERSION
    assert with_ttl() == []
    assert store.counts().chunk_events == 1
    assert store.migrate() == SCHEMA_VERSION  # repeatable


@pytest.mark.parametrize("retention_days", [7, 2])
def test_a_cloned_test_database_has_the_schema_the_migrations_make(chdb_dir, retention_days):
    """The store fixture's databases are cloned from a migrated template (tests/conftest.py
    `clone_migrated`): each table and view, and the migration log, as migrate() writes them
    (whatever the retention: the schema since v11 does not depend on it)."""
    from tests.conftest import clone_migrated

    migrated = ClickHouseStore(
        f"chdb://{chdb_dir}", database=f"m{next(_n)}", retention_days=retention_days
    )
    cloned = ClickHouseStore(f"chdb://{chdb_dir}", database=f"m{next(_n)}")
    try:
        migrated.migrate()
        clone_migrated(chdb_dir, cloned.database)

        def schema(store: ClickHouseStore) -> tuple:
            objects = store.client.query(
                "SELECT name, engine, replaceAll(create_table_query, {db:String}, 'DB.') "
                "FROM system.tables WHERE database = {d:String} ORDER BY name",
                parameters={"d": store.database, "db": f"{store.database}."},
            ).result_rows
            log = store.client.query(
                f"SELECT version, description, checksum FROM {store.database}.schema_migrations "
                "FINAL ORDER BY version"
            ).result_rows
            return objects, log

        assert schema(cloned) == schema(migrated)
        assert len(schema(cloned)[0]) > 30
        assert cloned.migrate() == SCHEMA_VERSION  # every migration found applied
    finally:
        migrated.close()
        cloned.close()
