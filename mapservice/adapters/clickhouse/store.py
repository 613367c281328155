"""ClickHouse behind the HistoryStore port, through clickhouse-connect.

The same code serves `chdb:///dir` (embedded chDB) and `http(s)://host:8123` (a server).
chDB allows one opener per directory and a client is not thread-safe, so each client is
used under its own lock (writes and snapshot building under one, reads under another, ping
on a client of its own: connection.py); callers in an event loop run these methods in an
executor.

`ClickHouseStore` is composed of one mixin per concern, each over the clients and locks of
`connection.ClickHouseConnection`: `migrations` (the schema and its lock), `writes`
(events, dead letters, conflicts), `snapshots` (building and repairing them), `reads`
(time travel and replay), `conflict_reads` (conflicts and the writes near chunks),
`change_feed` (map changes page by page), `annotation_reads` (operators' annotations), `legacy` (the 2019 REST queries), `retention`
(expiry that keeps the floor) and `admin` (deletes, counts,
optimize, ping, exports, close). This module only constructs it: the mixins never import
it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from mapservice.adapters.clickhouse.admin import AdminMixin
from mapservice.adapters.clickhouse.annotation_reads import AnnotationReadsMixin
from mapservice.adapters.clickhouse.change_feed import ChangeFeedMixin
from mapservice.adapters.clickhouse.command_reads import CommandReadsMixin
from mapservice.adapters.clickhouse.conflict_reads import ConflictReadsMixin
from mapservice.adapters.clickhouse.legacy import LegacyMixin
from mapservice.adapters.clickhouse.migrations import MigrationsMixin
from mapservice.adapters.clickhouse.reads import ReadsMixin
from mapservice.adapters.clickhouse.retention import RetentionMixin
from mapservice.adapters.clickhouse.snapshots import SnapshotsMixin
from mapservice.adapters.clickhouse.track_reads import TrackReadsMixin
from mapservice.adapters.clickhouse.vda_reads import VdaReadsMixin
from mapservice.adapters.clickhouse.writes import WritesMixin
from mapservice.adapters.clock import SystemClock, clock_from_settings
from mapservice.settings import Settings


class ClickHouseStore(
    MigrationsMixin,
    WritesMixin,
    ReadsMixin,
    ConflictReadsMixin,
    RetentionMixin,
    ChangeFeedMixin,
    SnapshotsMixin,
    LegacyMixin,
    VdaReadsMixin,
    AnnotationReadsMixin,
    AdminMixin,
    TrackReadsMixin,
    CommandReadsMixin,
):
    """Construction does no I/O; the first call connects."""

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
    ) -> None:
        self.dsn = dsn
        self.cluster = cluster  # non-empty: DDL ON CLUSTER, Replicated tables (schema_cluster)
        self.snapshot_every_ms = snapshot_every_ms
        self._last_snapshot_ms: int | None = None  # newest snapshot built, once known
        self._no_snapshot_until = 0.0  # monotonic time until which "no snapshot yet" holds
        self.database = database
        self.retention_days = retention_days
        self._username = username
        self._password = password
        self._client = None
        self._lock = threading.RLock()
        # Reads get a client of their own: an API read then runs beside an insert instead
        # of queueing behind it (chDB runs queries of two handles at once; measured: a
        # 3 ms read took ~9 ms beside a 150 ms query instead of waiting it out). Reads never
        # take `_lock`, so a writer that reads while holding it cannot deadlock with them.
        self._read_client = None
        self._read_lock = threading.Lock()
        self._ping_client = None
        # clickhouse-connect's TLS arguments (ca_cert, client_cert, client_cert_key) for an
        # https:// server (from_settings: MAPSERVICE_CLICKHOUSE_*_FILE).
        self.tls: dict[str, str] = dict(tls or {})
        # A server request that has not answered in this long fails (and is retried by its
        # caller): clickhouse-connect waits 300 s by default, and an insert hung on a server
        # that was restarting held the whole pipeline that long (fault tests).
        self.timeout_s = timeout_s
        self._known_contents: dict[bytes, int] = {}  # hash -> day already written
        # One reusable insert context per (table, columns): without it every insert first
        # asks the server for the table's column types (a DESCRIBE, ~3 ms on chDB).
        self._insert_contexts: dict[tuple[str, tuple[str, ...]], object] = {}
        # The service's clock (from_settings: a simulated one when settings ask for it);
        # the newest-first 2019 listing looks for its rows just before "now" on it.
        self.clock_ms: Callable[[], int] = SystemClock().now_ms

    @classmethod
    def from_settings(cls, settings: Settings) -> ClickHouseStore:
        store = cls(
            settings.resolved_clickhouse_dsn,
            settings.clickhouse_database,
            settings.retention_days,
            settings.clickhouse_username,
            settings.clickhouse_password.get_secret_value(),
            int(settings.snapshot_every_s * 1000),
            settings.clickhouse_cluster,
            tls=settings.clickhouse_tls(),
            timeout_s=settings.clickhouse_timeout_s,
        )
        store.clock_ms = clock_from_settings(settings).now_ms
        return store
