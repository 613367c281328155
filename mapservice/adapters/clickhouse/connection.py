"""The store's one connection to ClickHouse and the low-level helpers every role shares.

`ClickHouseConnection` is what each of the store's role adapters holds (as recorders share
one datastore): the database, the writer client (one at a time, under `lock`), the read
client (under a lock of its own), a ping client, reusable insert contexts, `rows` and
`pose_query` for reads, and what the process knows of the stored data that more than one
role needs (`known_contents`). The pure helpers that turn values into columns and columns
into PoseRows (`flag`, `unflag`, `mm`, `POSE_READ_COLUMNS`, `FINAL_SETTINGS`, `pose_rows`)
are here too. It depends only on clickhouse-connect, msgspec and the core's records, never
on another module of the store.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from contextlib import contextmanager
from typing import Any

import clickhouse_connect
import msgspec
import structlog

from mapservice.core.ports import PoseRow
from mapservice.settings import Settings

from .broken_parts import BrokenPartRecovery

log = structlog.get_logger(__name__)

json_encoder = msgspec.json.Encoder()
_BOOLISH = msgspec.json.Decoder(bool | str | None)


def flag(value: bool | str | None) -> str:
    # Stored as JSON text so the 2019 API can answer with the type the robot sent.
    if value is True:  # the usual two, spared the encoder: a batch flags every pose twice
        return "true"
    if value is False:
        return "false"
    return "" if value is None else json_encoder.encode(value).decode()


def unflag(text: str) -> bool | str | None:
    return None if text == "" else _BOOLISH.decode(text)


def mm(metres: float) -> int:
    return round(metres * 1000)


# A pose's columns as the reads select them. The path travels as one string ("x y,x y",
# millimetres; empty when has_path is false): parsing two Array columns costs the client far
# more than a String column, and most poses carry no path. Metres and the receive time are
# computed by ClickHouse (the same IEEE division and sum Python would do), which spares the
# client three passes over every row of a large read.
POSE_READ_COLUMNS = (
    "robot_id, toUnixTimestamp64Milli(ts), x_mm / 1000, y_mm / 1000, z_mm / 1000, "
    "qx, qy, qz, qw, battery, charging, loaded, has_path, if(has_path, "
    "arrayStringConcat(arrayMap((x, y) -> concat(toString(x), ' ', toString(y)), "
    "path_x_mm, path_y_mm), ','), ''), toUnixTimestamp64Milli(ts) + recv_lag_ms"
)
# Every FINAL read of poses and chunk_events: both are partitioned by the day of `ts`, a
# sorting-key column, so rows with one identity always share a partition and FINAL need
# not merge across partitions (it then skips merging single-part partitions entirely).
FINAL_SETTINGS = "SETTINGS do_not_merge_across_partitions_select_final = 1"


def _path(has_path: bool, text: str) -> tuple[tuple[float, float], ...] | None:
    if not has_path:
        return None
    if not text:
        return ()
    return tuple(
        (int(x) / 1000, int(y) / 1000) for x, y in (point.split(" ") for point in text.split(","))
    )


def pose_rows(columns: Sequence[Sequence]) -> list[PoseRow]:
    """PoseRows from the columns of a `POSE_READ_COLUMNS` query, column-wise (it is faster)."""
    if not columns or not len(columns[0]):
        return []
    robot, ts, x, y, z, qx, qy, qz, qw, battery, charging, loaded, has_path, path, received = (
        columns
    )
    flags: dict[str, bool | str | None] = {}

    def unflag_all(texts: Sequence[str]) -> list:
        return [flags[t] if t in flags else flags.setdefault(t, unflag(t)) for t in texts]

    paths = [_path(True, text) if has else None for has, text in zip(has_path, path)]
    return list(
        map(
            PoseRow,
            robot,
            ts,
            x,
            y,
            z,
            qx,
            qy,
            qz,
            qw,
            battery,
            unflag_all(charging),
            unflag_all(loaded),
            paths,
            received,
        )
    )


class ClickHouseConnection:
    """The clients and locks the store's roles share; construction does no I/O, the first
    call connects.

    chDB allows one opener per directory and a client is not thread-safe, so each client is
    used under its own lock: writes, schema changes and snapshot building under `lock`,
    reads under the read client's, ping on a client of its own. Callers in an event loop
    run the roles' methods in an executor."""

    def __init__(
        self,
        dsn: str,
        database: str = "mapservice",
        retention_days: int = 7,
        username: str = "default",
        password: str = "",
        cluster: str = "",
        tls: dict[str, str] | None = None,
        timeout_s: float = 60.0,
    ) -> None:
        self.dsn = dsn
        self.database = database
        self.retention_days = retention_days
        self.cluster = cluster  # non-empty: DDL ON CLUSTER, Replicated tables (schema_cluster)
        self._username = username
        self._password = password
        self._client: Any = None
        self.lock = threading.RLock()
        # Reads get a client of their own: an API read then runs beside an insert instead
        # of queueing behind it (chDB runs queries of two handles at once; measured: a
        # 3 ms read took ~9 ms beside a 150 ms query instead of waiting it out). Reads never
        # take `lock`, so a writer that reads while holding it cannot deadlock with them.
        self._read_client: Any = None
        self._read_lock = threading.Lock()
        self._ping_client: Any = None
        # clickhouse-connect's TLS arguments (ca_cert, client_cert, client_cert_key) for an
        # https:// server (from_settings: MAPSERVICE_CLICKHOUSE_*_FILE).
        self.tls: dict[str, str] = dict(tls or {})
        # A server request that has not answered in this long fails (and is retried by its
        # caller): clickhouse-connect waits 300 s by default, and an insert hung on a server
        # that was restarting held the whole pipeline that long (fault tests).
        self.timeout_s = timeout_s
        # Content hash -> the day it was last written: the writer skips pixels already
        # stored that day, the retention forgets what it renews (both under `lock`).
        self.known_contents: dict[bytes, int] = {}
        # One reusable insert context per (table, columns): without it every insert first
        # asks the server for the table's column types (a DESCRIBE, ~3 ms on chDB).
        self._insert_contexts: dict[tuple[str, tuple[str, ...], bool], object] = {}
        # Created on the first failed write to chDB (broken_parts.py); kept for its cooldowns.
        self._broken_parts: BrokenPartRecovery | None = None

    @classmethod
    def from_settings(cls, settings: Settings) -> ClickHouseConnection:
        return cls(
            settings.resolved_clickhouse_dsn,
            settings.clickhouse_database,
            settings.retention_days,
            settings.clickhouse_username,
            settings.clickhouse_password.get_secret_value(),
            settings.clickhouse_cluster,
            tls=settings.clickhouse_tls(),
            timeout_s=settings.clickhouse_timeout_s,
        )

    def connect(self):
        if self.dsn.startswith("chdb://"):
            try:
                import chdb  # noqa: F401  (clickhouse-connect loads it; say what to do if absent)
            except ImportError as exc:
                raise RuntimeError(
                    "embedded ClickHouse (chdb://) needs the embedded extra: pip install "
                    "'mapservice[embedded]'; or point MAPSERVICE_CLICKHOUSE_DSN at a server"
                ) from exc
            return clickhouse_connect.get_client(dsn=self.dsn)
        return clickhouse_connect.get_client(
            dsn=self.dsn,
            username=self._username,
            password=self._password,
            connect_timeout=min(10.0, self.timeout_s),
            send_receive_timeout=self.timeout_s,
            **self.tls,
        )

    @property
    def client(self):
        """The client for writes, schema changes and snapshot building (under `lock`)."""
        with self.lock:
            if self._client is None:
                self._client = self.connect()
            return self._client

    @contextmanager
    def reader(self):
        """The read client, held for one read. A read that meets a part a full disk cut
        short reloads its table as a write does (after the read client is released)."""
        with self.reloading_broken_tables(), self._read_lock:
            if self._read_client is None:
                self._read_client = self.connect()
            yield self._read_client

    @contextmanager
    def reloading_broken_tables(self):
        """Around a write or a read: when it fails because chDB cannot read a part (one a
        full disk cut short), reloads the tables the error names with the writer client,
        so that the caller's retry finds the part set aside (broken_parts.py). The failure
        is raised still: the caller records it and retries. A ClickHouse server is left
        alone."""
        try:
            yield
        except Exception as exc:
            if self.dsn.startswith("chdb://"):
                with self.lock:
                    if self._broken_parts is None:
                        self._broken_parts = BrokenPartRecovery(
                            self.database,
                            lambda sql: self.client.command(sql),
                            lambda sql: self.client.query(sql).result_rows,
                        )
                    try:
                        if self._broken_parts.after_failure(exc):
                            self._insert_contexts.clear()  # they name the tables reloaded
                    except Exception as failed:  # noqa: BLE001 - the write's error is the one to raise
                        log.error("reloading tables with broken parts failed", error=str(failed))
            raise

    def insert(
        self,
        table: str,
        rows: Sequence[Sequence],
        columns: Sequence[str],
        *,
        column_oriented: bool = False,
    ) -> None:
        """Inserts `rows` into `table` of the database with the writer client (under `lock`).
        With `column_oriented`, `rows` is one sequence per column instead (in `columns`
        order): a writer that builds columns spares the client turning rows into them."""
        key = (table, tuple(columns), column_oriented)
        with self.reloading_broken_tables():
            context = self._insert_contexts.get(key)
            if context is None:
                context = self.client.create_insert_context(
                    f"{self.database}.{table}", list(columns), column_oriented=column_oriented
                )
                self._insert_contexts[key] = context
            self.client.insert(data=rows, context=context)

    def forget_insert_contexts(self) -> None:
        """After a schema change: the column types the contexts hold may be stale."""
        self._insert_contexts.clear()

    def rows(self, sql: str, params: dict, **query_options) -> list[tuple]:
        with self.reader() as c:
            return c.query(sql, parameters=params, **query_options).result_rows

    def valid_before(self) -> str:
        """SQL for the first instant whose snapshots may be wrong (a pending repair's
        start), or far in the future: reads (the snapshots' own and the change feed's) use only
        snapshots before it."""
        # minOrNull: min() of no rows is the epoch, not NULL, which made every snapshot
        # invalid while no repair was pending (every read folded the whole history).
        return (
            f"(SELECT ifNull(minOrNull(from_ts), "
            f"toDateTime64('2299-12-31 00:00:00', 3, 'UTC')) FROM {self.database}.snapshot_repairs)"
        )

    def pose_query(self, sql: str, params: dict) -> list[PoseRow]:
        with self.reader() as c:
            columns = c.query(sql, parameters=params).result_columns
        return pose_rows(columns)

    def ping(self, timeout_s: float = 2.0) -> bool:
        """A real round trip to ClickHouse on a client of its own (a hung server must not
        hold the read or write client); readiness calls it through a CachedCheck."""
        if self._ping_client is None:
            if self.dsn.startswith("chdb://"):
                self._ping_client = self.connect()
            else:
                self._ping_client = clickhouse_connect.get_client(
                    dsn=self.dsn,
                    username=self._username,
                    password=self._password,
                    connect_timeout=timeout_s,
                    send_receive_timeout=timeout_s,
                    **self.tls,
                )
        return self._ping_client.command("SELECT 1") == 1

    def close(self) -> None:
        with self.lock, self._read_lock:
            for client in (self._client, self._read_client):
                if client is not None:
                    client.close()
            self._client = self._read_client = None
