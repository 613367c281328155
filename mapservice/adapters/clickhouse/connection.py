"""The store's connection to ClickHouse and the low-level helpers every part of it shares.

`ClickHouseConnection` is the base of each of the store's mixins: the writer client (one
at a time, under `_lock`), the read client (under `_read_lock`), reusable insert contexts,
`_rows` and `_pose_query` for reads, and the pure helpers that turn values into columns and
columns into PoseRows (`_flag`, `_unflag`, `_mm`, `_POSE_COLUMNS`, `_FINAL_SETTINGS`,
`_pose_rows`, ...). It depends only on clickhouse-connect, msgspec and the core's records,
never on another module of the store.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from contextlib import contextmanager

import clickhouse_connect
import msgspec
import structlog

from mapservice.core.ports import PoseRow

from .broken_parts import BrokenPartRecovery

log = structlog.get_logger(__name__)

_json = msgspec.json.Encoder()
_BOOLISH = msgspec.json.Decoder(bool | str | None)


def _flag(value: bool | str | None) -> str:
    # Stored as JSON text so the 2019 API can answer with the type the robot sent.
    return "" if value is None else _json.encode(value).decode()


def _unflag(text: str) -> bool | str | None:
    return None if text == "" else _BOOLISH.decode(text)


def _mm(metres: float) -> int:
    return round(metres * 1000)


# A pose's columns as the reads select them. The path travels as one string ("x y,x y",
# millimetres; empty when has_path is false): parsing two Array columns costs the client far
# more than a String column, and most poses carry no path. Metres and the receive time are
# computed by ClickHouse (the same IEEE division and sum Python would do), which spares the
# client three passes over every row of a large read.
_POSE_COLUMNS = (
    "robot_id, toUnixTimestamp64Milli(ts), x_mm / 1000, y_mm / 1000, z_mm / 1000, "
    "qx, qy, qz, qw, battery, charging, loaded, has_path, if(has_path, "
    "arrayStringConcat(arrayMap((x, y) -> concat(toString(x), ' ', toString(y)), "
    "path_x_mm, path_y_mm), ','), ''), toUnixTimestamp64Milli(ts) + recv_lag_ms"
)
# Every FINAL read of poses and chunk_events: both are partitioned by the day of `ts`, a
# sorting-key column, so rows with one identity always share a partition and FINAL need
# not merge across partitions (it then skips merging single-part partitions entirely).
_FINAL_SETTINGS = "SETTINGS do_not_merge_across_partitions_select_final = 1"


def _path(has_path: bool, text: str) -> tuple[tuple[float, float], ...] | None:
    if not has_path:
        return None
    if not text:
        return ()
    return tuple(
        (int(x) / 1000, int(y) / 1000) for x, y in (point.split(" ") for point in text.split(","))
    )


def _pose_rows(columns: Sequence[Sequence]) -> list[PoseRow]:
    """PoseRows from the columns of a `_POSE_COLUMNS` query, column-wise (it is faster)."""
    if not columns or not len(columns[0]):
        return []
    robot, ts, x, y, z, qx, qy, qz, qw, battery, charging, loaded, has_path, path, received = (
        columns
    )
    flags: dict[str, bool | str | None] = {}

    def unflag(texts: Sequence[str]) -> list:
        return [flags[t] if t in flags else flags.setdefault(t, _unflag(t)) for t in texts]

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
            unflag(charging),
            unflag(loaded),
            paths,
            received,
        )
    )


class ClickHouseConnection:
    """The clients and locks the store's mixins share. ClickHouseStore.__init__ sets the
    attributes below (construction does no I/O); the first call connects."""

    dsn: str
    database: str
    retention_days: int
    _username: str
    _password: str
    _client: object | None
    _lock: threading.RLock
    _read_client: object | None
    tls: dict[str, str]
    timeout_s: float
    _read_lock: threading.Lock
    _insert_contexts: dict[tuple[str, tuple[str, ...]], object]
    # Created on the first failed write to chDB (broken_parts.py); kept for its cooldowns.
    _broken_parts: BrokenPartRecovery | None = None

    def _connect(self):
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
        """The client for writes, schema changes and snapshot building (under `_lock`)."""
        with self._lock:
            if self._client is None:
                self._client = self._connect()
            return self._client

    @contextmanager
    def _reader(self):
        """The read client, held for one read. A read that meets a part a full disk cut
        short reloads its table as a write does (after the read client is released)."""
        with self._reloading_broken_tables(), self._read_lock:
            if self._read_client is None:
                self._read_client = self._connect()
            yield self._read_client

    @contextmanager
    def _reloading_broken_tables(self):
        """Around a write or a read: when it fails because chDB cannot read a part (one a
        full disk cut short), reloads the tables the error names with the writer client,
        so that the caller's retry finds the part set aside (broken_parts.py). The failure
        is raised still: the caller records it and retries. A ClickHouse server is left
        alone."""
        try:
            yield
        except Exception as exc:
            if self.dsn.startswith("chdb://"):
                with self._lock:
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

    def _insert(self, table: str, rows: Sequence[Sequence], columns: Sequence[str]) -> None:
        """Inserts `rows` into `table` of the database with the writer client (under `_lock`)."""
        key = (table, tuple(columns))
        with self._reloading_broken_tables():
            context = self._insert_contexts.get(key)
            if context is None:
                context = self.client.create_insert_context(
                    f"{self.database}.{table}", list(columns)
                )
                self._insert_contexts[key] = context
            self.client.insert(data=rows, context=context)

    def _rows(self, sql: str, params: dict, **query_options) -> list[tuple]:
        with self._reader() as c:
            return c.query(sql, parameters=params, **query_options).result_rows

    def _valid_before(self) -> str:
        """SQL for the first instant whose snapshots may be wrong (a pending repair's
        start), or far in the future: reads (the snapshots' own and the change feed's) use only
        snapshots before it."""
        # minOrNull: min() of no rows is the epoch, not NULL, which made every snapshot
        # invalid while no repair was pending (every read folded the whole history).
        return (
            f"(SELECT ifNull(minOrNull(from_ts), "
            f"toDateTime64('2299-12-31 00:00:00', 3, 'UTC')) FROM {self.database}.snapshot_repairs)"
        )

    def _pose_query(self, sql: str, params: dict) -> list[PoseRow]:
        with self._reader() as c:
            columns = c.query(sql, parameters=params).result_columns
        return _pose_rows(columns)
