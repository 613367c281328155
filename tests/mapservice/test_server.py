"""In production mode a component waits for `mapservice migrate` instead of migrating."""

from __future__ import annotations

import asyncio

from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.server import wait_for_schema
from mapservice.settings import Settings


class VersionsStore:
    """A store whose schema version moves through `versions`, one per look."""

    def __init__(self, *versions: int):
        self.versions = list(versions)
        self.looks = 0
        self.migrated = False

    def schema_version(self) -> int:
        self.looks += 1
        return self.versions.pop(0) if len(self.versions) > 1 else self.versions[0]

    def migrate(self) -> int:  # must never be called here
        self.migrated = True
        return SCHEMA_VERSION


def test_waits_until_the_migration_brought_the_schema_to_this_release() -> None:
    """Versions 0, 6, then this release's: returns on the third look, never migrates."""
    store = VersionsStore(0, SCHEMA_VERSION - 1, SCHEMA_VERSION)
    assert asyncio.run(wait_for_schema(store, every_s=0.01)) == SCHEMA_VERSION
    assert store.looks == 3 and not store.migrated


def test_a_newer_schema_does_not_block() -> None:
    """A schema ahead of this release (a newer release migrated) is accepted at once."""
    assert (
        asyncio.run(wait_for_schema(VersionsStore(SCHEMA_VERSION + 1), every_s=0.01))
        == SCHEMA_VERSION + 1
    )


def test_only_local_mode_migrates_on_start_by_default() -> None:
    """local: migrate on start; production: not, unless MAPSERVICE_MIGRATE_ON_START says so."""
    assert Settings(mode="local").migrates_on_start is True
    production = {
        "mode": "production",
        "admin_token": "t" * 32,
        "clickhouse_dsn": "http://ch:8123",
        "clickhouse_password": "p" * 16,
    }
    assert Settings(**production).migrates_on_start is False
    assert Settings(**production, migrate_on_start=True).migrates_on_start is True


def test_live_stream_compression_is_off_unless_configured() -> None:
    """uvicorn offers permessage-deflate on the live WebSocket only with api_live_compression."""
    from mapservice.api.app import create_app
    from mapservice.api.composition import api_server_config
    from mapservice.settings import Settings
    from mapservice.testing.memory_store import MemoryStore

    for flag in (False, True):
        settings = Settings(api_live_compression=flag)
        assert (
            api_server_config(
                create_app(settings, MemoryStore(), {}), settings
            ).ws_per_message_deflate
            is flag
        )
