"""ClickHouse behind the store's role ports, through clickhouse-connect.

The same code serves `chdb:///dir` (embedded chDB) and `http(s)://host:8123` (a server).
One `connection.ClickHouseConnection` holds the clients, their locks and the database;
each role of the store (mapservice/core/ports.py) is an adapter of its own over it, in its
own module: `migrations` (StoreSchema), `writes` (HistoryWriter), `reads` (TimeTravelReader,
with `track_reads`), `snapshots` (SnapshotKeeper), `retention` (RetentionKeeper),
`conflict_reads` (ConflictReader), `annotation_reads` (AnnotationReader), `incident_reads`
(IncidentReader), `heatmap_reads` (HeatmapReader), `command_reads` (CommandReader),
`vda_reads` (VdaReader), `webhook_registry` (WebhookRegistry), `change_feed` (ChangeFeed),
`legacy` (the 2019 REST listings) and `admin` (StoreAdmin, TableExports).

`clickhouse_roles` builds them over one connection, sharing what two roles must share (the
snapshot keeper that knows the newest snapshot): what a composition root hands out, one
role to each component. `ClickHouseStore` is every role at once, for what uses the store
whole: tests, benchmarks and loaders, the CLI's one-shot commands.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mapservice.adapters.clickhouse.admin import ClickHouseAdmin
from mapservice.adapters.clickhouse.annotation_reads import ClickHouseAnnotationReads
from mapservice.adapters.clickhouse.change_feed import ClickHouseChangeFeed
from mapservice.adapters.clickhouse.command_reads import ClickHouseCommandReads
from mapservice.adapters.clickhouse.conflict_reads import ClickHouseConflictReads
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.adapters.clickhouse.heatmap_reads import ClickHouseHeatmapReads
from mapservice.adapters.clickhouse.incident_reads import ClickHouseIncidentReads
from mapservice.adapters.clickhouse.legacy import ClickHouseLegacyQueries
from mapservice.adapters.clickhouse.migrations import ClickHouseSchema
from mapservice.adapters.clickhouse.reads import ClickHouseTimeTravel
from mapservice.adapters.clickhouse.retention import ClickHouseRetention
from mapservice.adapters.clickhouse.snapshots import ClickHouseSnapshots
from mapservice.adapters.clickhouse.track_reads import ClickHouseTrackReads
from mapservice.adapters.clickhouse.vda_reads import ClickHouseVdaReads
from mapservice.adapters.clickhouse.webhook_registry import ClickHouseWebhookRegistry
from mapservice.adapters.clickhouse.writes import ClickHouseHistoryWriter
from mapservice.adapters.clock import clock_from_settings
from mapservice.core.heatmaps import HeatmapRule
from mapservice.core.store_roles import StoreRoles
from mapservice.settings import Settings


def clickhouse_roles(
    connection: ClickHouseConnection,
    snapshot_every_ms: int = 600_000,
    clock_ms: Callable[[], int] | None = None,
    heatmap_rule: HeatmapRule | None = None,
) -> StoreRoles:
    """Every role of the store over `connection`, each an adapter of its own. `clock_ms` is
    the service's clock (the newest-first 2019 listing looks just before "now" on it);
    `heatmap_rule` the thresholds the heatmaps are built and read with."""
    rule = heatmap_rule or HeatmapRule()
    snapshots = ClickHouseSnapshots(connection, snapshot_every_ms, rule)
    conflicts = ClickHouseConflictReads(connection)
    admin = ClickHouseAdmin(connection)
    return StoreRoles(
        schema=ClickHouseSchema(connection),
        writer=ClickHouseHistoryWriter(connection, snapshots),
        history=ClickHouseTimeTravel(connection, conflicts, ClickHouseTrackReads(connection)),
        snapshots=snapshots,
        retention=ClickHouseRetention(connection, snapshots),
        conflicts=conflicts,
        annotations=ClickHouseAnnotationReads(connection),
        incidents=ClickHouseIncidentReads(connection),
        heatmaps=ClickHouseHeatmapReads(connection, rule),
        commands=ClickHouseCommandReads(connection),
        vda=ClickHouseVdaReads(connection),
        webhooks=ClickHouseWebhookRegistry(connection),
        changes=ClickHouseChangeFeed(connection),
        legacy=ClickHouseLegacyQueries(connection, clock_ms),
        admin=admin,
        exports=admin,
    )


def clickhouse_roles_from_settings(
    settings: Settings, connection: ClickHouseConnection | None = None
) -> StoreRoles:
    """`clickhouse_roles` as the settings configure them (over a new connection unless one
    is given): the snapshot interval, the service's clock and the incidents' thresholds."""
    return clickhouse_roles(
        connection or ClickHouseConnection.from_settings(settings),
        int(settings.snapshot_every_s * 1000),
        clock_from_settings(settings).now_ms,
        heatmap_rule_of(settings),
    )


def heatmap_rule_of(settings: Settings) -> HeatmapRule:
    """The heatmaps' thresholds: the incidents' moving speed and offline silence."""
    return HeatmapRule(settings.incident_moving_m_s, round(settings.robot_offline_after_s * 1000))


class ClickHouseStore:
    """Every role of the store over one connection, answering each role's methods (and the
    connection's attributes) as one object: for tests, benchmarks and tools that use the
    store whole. No component is handed it: composition roots hand out `roles`' fields.
    Construction does no I/O; the first call connects."""

    def __init__(
        self,
        dsn: str,
        database: str = "mapservice",
        retention_days: int = 7,
        username: str = "default",
        password: str = "",
        snapshot_every_ms: int = 600_000,
        cluster: str = "",
        tls: dict[str, str] | None = None,
        timeout_s: float = 60.0,
        clock_ms: Callable[[], int] | None = None,
    ) -> None:
        connection = ClickHouseConnection(
            dsn, database, retention_days, username, password, cluster, tls, timeout_s
        )
        self._adopt(connection, clickhouse_roles(connection, snapshot_every_ms, clock_ms))

    @classmethod
    def from_settings(cls, settings: Settings) -> ClickHouseStore:
        connection = ClickHouseConnection.from_settings(settings)
        store = cls.__new__(cls)
        store._adopt(connection, clickhouse_roles_from_settings(settings, connection))
        return store

    def _adopt(self, connection: ClickHouseConnection, roles: StoreRoles) -> None:
        object.__setattr__(self, "connection", connection)
        object.__setattr__(self, "roles", roles)
        # Where a name is looked up: each role's adapter (the first that has it), then the
        # connection (database, dsn, client, ping, ...).
        parts = [getattr(roles, f) for f in roles.__dataclass_fields__]
        object.__setattr__(self, "_parts", (*(p for p in parts if p is not None), connection))

    def __getattr__(self, name: str) -> Any:
        # Only called for names not found on the store itself: the parts' members.
        if name.startswith("__"):
            raise AttributeError(name)
        for part in self.__dict__.get("_parts", ()):
            if hasattr(part, name):
                return getattr(part, name)
        raise AttributeError(f"no role of the ClickHouse store has {name!r}")

    def __setattr__(self, name: str, value: object) -> None:
        # A setting (snapshot_every_ms, clock_ms, cluster) is changed where it lives.
        for part in self._parts:
            if hasattr(part, name):
                setattr(part, name, value)
                return
        object.__setattr__(self, name, value)

    def __repr__(self) -> str:
        return f"<ClickHouseStore {self.connection.database} at {self.connection.dsn}>"
