"""ClickHouse's roles are adapters of their own over one connection: each answers its role
and no other in full, all hold the same connection, and what the processors build over
them (as the process entry hands them) leads to no whole store. Construction does no I/O,
so nothing here connects."""

from __future__ import annotations

import dataclasses

import pytest

import mapservice.processors.composition as processors_composition
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.adapters.clickhouse.store import ClickHouseStore, clickhouse_roles
from mapservice.core import ports
from mapservice.core.store_roles import StoreRoles, role_members
from mapservice.settings import Settings
from tests.test_composition_roots import ROLES, paths_to_whole_store, roles_answered

# Each StoreRoles field and the role protocol its value answers.
FIELD_ROLES = {
    f.name: getattr(ports, str(f.type).split(" | ")[0]) for f in dataclasses.fields(StoreRoles)
}


def _connection() -> ClickHouseConnection:
    return ClickHouseConnection("http://127.0.0.1:1", database="unused")


@pytest.mark.parametrize("field", sorted(FIELD_ROLES))
def test_each_role_is_an_adapter_of_its_own_over_the_one_connection(field: str) -> None:
    connection = _connection()
    roles = clickhouse_roles(connection)
    adapter = getattr(roles, field)
    role = FIELD_ROLES[field]
    assert all(hasattr(adapter, m) for m in role_members(role)), role.__name__
    # No other role in full (the admin also answers the exports, which no component takes
    # as a store role).
    answered = roles_answered(adapter)
    assert answered == ([role.__name__] if role in ROLES else ["StoreAdmin"]), answered
    assert adapter.connection is connection
    # A plain adapter, not a view over a whole store.
    assert type(adapter).__module__.startswith("mapservice.adapters.clickhouse.")


def test_the_roles_that_share_state_share_one_keeper() -> None:
    """The writer notes repairs on, and the retention anchors at, the snapshots the snapshot
    timer builds: one keeper, so what one knows of the newest snapshot the others see."""
    roles = clickhouse_roles(_connection())
    assert roles.writer.snapshots is roles.snapshots
    assert roles.retention.snapshots is roles.snapshots


def test_the_whole_store_is_its_roles_over_one_connection() -> None:
    """ClickHouseStore (tests and tools) answers every role through the same adapters, and
    a setting changed on it changes where it lives."""
    store = ClickHouseStore("http://127.0.0.1:1", database="unused", snapshot_every_ms=1_000)
    assert store.database == "unused" and store.connection.database == "unused"
    assert store.poses.__self__ is store.roles.history
    assert store.build_snapshots.__self__ is store.roles.snapshots
    store.snapshot_every_ms = 60_000
    assert store.roles.snapshots.snapshot_every_ms == 60_000
    with pytest.raises(AttributeError, match="no role of the ClickHouse store"):
        store.no_such_method  # noqa: B018


def test_the_processors_over_clickhouse_roles_hold_no_whole_store(tmp_path) -> None:
    """The process entry hands the processors the ClickHouse roles: nothing they build
    leads to an object answering more than one role."""
    settings = Settings(
        kafka_bootstrap="127.0.0.1:1", mqtt_url="mqtt://127.0.0.1:1", data_dir=tmp_path
    )
    roles = clickhouse_roles(_connection())
    parts = processors_composition.compose_processors(settings, roles)
    try:
        assert paths_to_whole_store(parts, object(), "processors") == []
        assert parts.sink.writer is roles.writer
    finally:
        parts.store_thread.close()
        parts.views.close()
