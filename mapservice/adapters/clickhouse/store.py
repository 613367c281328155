"""ClickHouse behind the HistoryStore port, through clickhouse-connect.

The same code serves `chdb:///dir` (embedded chDB) and `http(s)://host:8123` (a server).
chDB allows one opener per directory and its client is not thread-safe, so every call
goes through one lock; callers in an event loop run these methods in an executor.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from datetime import datetime, timezone

import clickhouse_connect
import clickhouse_connect.driver.exceptions
import msgspec
import structlog

from mapservice.core.events import ChunkUpdated, DeadLetter, Envelope, MapMetaSet, PoseReported
from mapservice.core.legacy_query import ChunkQuery, PoseQuery, sort_column
from mapservice.core.ports import ChunkRow, ConflictRow, Counts, PoseRow, TimelineBucket
from mapservice.core.ports import ChunkState
from mapservice.core.timetravel import timeline_buckets
from mapservice.adapters.clickhouse.schema import KEYFRAME_MS, POSE_COLUMNS, checksums, migrations
from mapservice.adapters.clickhouse.cluster import for_cluster
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

_json = msgspec.json.Encoder()
_BOOLISH = msgspec.json.Decoder(bool | str | None)


def _flag(value: bool | str | None) -> str:
    # Stored as JSON text so the 2019 API can answer with the type the robot sent.
    return "" if value is None else _json.encode(value).decode()


def _unflag(text: str) -> bool | str | None:
    return None if text == "" else _BOOLISH.decode(text)


def _ms(dt: datetime) -> int:
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return int(round(dt.timestamp() * 1000))


def _mm(metres: float) -> int:
    return int(round(metres * 1000))


# A pose's columns as the reads select them. The path travels as one string ("x y,x y",
# millimetres; empty when has_path is false): parsing two Array columns costs the client far
# more than a String column, and most poses carry no path.
_POSE_COLUMNS = ("robot_id, toUnixTimestamp64Milli(ts), x_mm, y_mm, z_mm, qx, qy, qz, qw, battery, "
                 "charging, loaded, has_path, if(has_path, arrayStringConcat(arrayMap((x, y) -> "
                 "concat(toString(x), ' ', toString(y)), path_x_mm, path_y_mm), ','), ''), "
                 "recv_lag_ms")
# Every FINAL read of poses and chunk_events: both are partitioned by the day of `ts`, a
# sorting-key column, so rows with one identity always share a partition and FINAL need
# not merge across partitions (it then skips merging single-part partitions entirely).
_FINAL_SETTINGS = "SETTINGS do_not_merge_across_partitions_select_final = 1"
NO_SNAPSHOT_RECHECK_S = 5.0


def _path(has_path: bool, text: str) -> tuple[tuple[float, float], ...] | None:
    if not has_path:
        return None
    if not text:
        return ()
    return tuple((int(x) / 1000, int(y) / 1000)
                 for x, y in (point.split(" ") for point in text.split(",")))


def _pose_rows(columns: Sequence[Sequence]) -> list[PoseRow]:
    """PoseRows from the columns of a `_POSE_COLUMNS` query, column-wise (it is faster)."""
    if not columns or not len(columns[0]):
        return []
    robot, ts, x, y, z, qx, qy, qz, qw, battery, charging, loaded, has_path, path, lag = columns
    flags: dict[str, bool | str | None] = {}

    def unflag(texts: Sequence[str]) -> list:
        return [flags[t] if t in flags else flags.setdefault(t, _unflag(t)) for t in texts]

    return list(map(
        PoseRow, robot, ts, [v / 1000 for v in x], [v / 1000 for v in y], [v / 1000 for v in z],
        qx, qy, qz, qw, battery, unflag(charging), unflag(loaded), map(_path, has_path, path),
        [t + lag_ms for t, lag_ms in zip(ts, lag)]))


MIGRATION_LOCK = "schema_migration_lock"


class MigrationLocked(RuntimeError):
    """Another migrator holds the lock past the timeout."""


class MigrationChanged(RuntimeError):
    """An applied migration's statements differ from this release's."""


class ClickHouseStore:
    """Construction does no I/O; the first call connects."""

    def __init__(self, dsn: str, database: str = "mapservice", retention_days: int = 7,
                 username: str = "default", password: str = "",
                 snapshot_every_ms: int = 600_000, cluster: str = "") -> None:
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
        # https:// server; from_settings fills them from MAPSERVICE_CLICKHOUSE_*_FILE.
        self.tls: dict[str, str] = {}
        self._known_contents: dict[bytes, int] = {}  # hash -> day already written
        # One reusable insert context per (table, columns): without it every insert first
        # asks the server for the table's column types (a DESCRIBE, ~3 ms on chDB).
        self._insert_contexts: dict[tuple[str, tuple[str, ...]], object] = {}

    @classmethod
    def from_settings(cls, settings: Settings) -> "ClickHouseStore":
        store = cls(
            settings.resolved_clickhouse_dsn,
            settings.clickhouse_database,
            settings.retention_days,
            settings.clickhouse_username,
            settings.clickhouse_password.get_secret_value(),
            int(settings.snapshot_every_s * 1000),
            settings.clickhouse_cluster,
        )
        store.tls = settings.clickhouse_tls()
        return store

    def _connect(self):
        if self.dsn.startswith("chdb://"):
            try:
                import chdb  # noqa: F401  (clickhouse-connect loads it; say what to do if absent)
            except ImportError as exc:
                raise RuntimeError(
                    "embedded ClickHouse (chdb://) needs the embedded extra: pip install "
                    "'mapservice[embedded]'; or point MAPSERVICE_CLICKHOUSE_DSN at a server") from exc
            return clickhouse_connect.get_client(dsn=self.dsn)
        return clickhouse_connect.get_client(dsn=self.dsn, username=self._username,
                                             password=self._password, **self.tls)

    @property
    def client(self):
        """The client for writes, schema changes and snapshot building (under `_lock`)."""
        with self._lock:
            if self._client is None:
                self._client = self._connect()
            return self._client

    @contextmanager
    def _reader(self):
        """The read client, held for one read."""
        with self._read_lock:
            if self._read_client is None:
                self._read_client = self._connect()
            yield self._read_client

    def _insert(self, table: str, rows: Sequence[Sequence], columns: Sequence[str]) -> None:
        """Inserts `rows` into `table` of the database with the writer client (under `_lock`)."""
        key = (table, tuple(columns))
        context = self._insert_contexts.get(key)
        if context is None:
            context = self.client.create_insert_context(f"{self.database}.{table}", list(columns))
            self._insert_contexts[key] = context
        self.client.insert(data=rows, context=context)

    # --- schema ---------------------------------------------------------------------

    def schema_version(self) -> int:
        """The highest applied migration (0 on an empty database)."""
        try:
            (version,), = self._rows(f"SELECT max(version) FROM {self.database}.schema_migrations", {})
        except Exception:  # no database or table yet
            return 0
        return int(version or 0)

    def migrate(self, lock_timeout_s: float = 600.0, holder: str | None = None) -> int:
        """Applies the migrations not applied yet, under a lock, and returns the version.

        The lock is a table that only one `CREATE TABLE` can create (ClickHouse refuses the
        second with TABLE_ALREADY_EXISTS): two migrators never interleave statements, the
        second waits and then finds everything applied. Each applied migration keeps a
        checksum of its statements; a migration edited after it ran is an error."""
        db = self.database
        holder = holder or f"{socket.gethostname()}:{os.getpid()}"
        with self._lock:
            c = self.client
            ddl = self._ddl
            ddl(f"CREATE DATABASE IF NOT EXISTS {db}")
            ddl(f"CREATE TABLE IF NOT EXISTS {db}.schema_migrations (version UInt32, "
                "description String, applied DateTime DEFAULT now()) "
                "ENGINE = ReplacingMergeTree ORDER BY version")
            ddl(f"ALTER TABLE {db}.schema_migrations ADD COLUMN IF NOT EXISTS "
                "checksum String DEFAULT ''")
            self._take_migration_lock(holder, lock_timeout_s)
            try:
                applied = dict(c.query(f"SELECT version, checksum FROM {db}.schema_migrations FINAL")
                               .result_rows)
                version = max(applied, default=0)
                released = checksums()
                for m in migrations(db, self.retention_days):
                    if m.version in applied:
                        if applied[m.version] and applied[m.version] != released[m.version]:
                            raise MigrationChanged(
                                f"schema migration {m.version} ({m.description}) differs from the "
                                "one applied to this database; migrations must never change once "
                                "released: add a new one instead")
                        continue
                    log.info("applying schema migration", version=m.version, description=m.description)
                    for statement in m.statements:
                        ddl(statement)
                    c.insert(f"{db}.schema_migrations", [[m.version, m.description, released[m.version]]],
                             column_names=["version", "description", "checksum"])
                    version = max(version, m.version)
            finally:
                ddl(f"DROP TABLE IF EXISTS {db}.{MIGRATION_LOCK} SYNC")
            self._insert_contexts.clear()  # column types may have changed
            return version

    def _ddl(self, statement: str) -> None:
        """A schema statement, ON CLUSTER with Replicated engines where a cluster is set."""
        self.client.command(for_cluster(statement, self.cluster))

    def _take_migration_lock(self, holder: str, timeout_s: float) -> None:
        db, c = self.database, self.client
        deadline = time.monotonic() + timeout_s
        waited = False
        while True:
            try:
                # Log, not MergeTree: on a cluster each replica has its own lock table,
                # and ON CLUSTER DDL runs in one queue, so one CREATE still wins.
                self._ddl(f"CREATE TABLE {db}.{MIGRATION_LOCK} (holder String, since DateTime "
                          "DEFAULT now()) ENGINE = Log")
                c.insert(f"{db}.{MIGRATION_LOCK}", [[holder]], column_names=["holder"])
                return
            except clickhouse_connect.driver.exceptions.DatabaseError as exc:
                if "already exists" not in str(exc).lower() and "(57)" not in str(exc) \
                        and "code: 57" not in str(exc).lower():
                    raise
            rows = c.query(f"SELECT holder, since FROM {db}.{MIGRATION_LOCK}").result_rows
            who = f"{rows[0][0]} since {rows[0][1]} UTC" if rows else "another migrator"
            if time.monotonic() > deadline:
                raise MigrationLocked(
                    f"schema migrations are locked by {who}; if that process is gone, run "
                    f"`mapservice migrate --break-lock` (drops {db}.{MIGRATION_LOCK})")
            if not waited:
                log.info("waiting for another schema migration", holder=who)
                waited = True
            time.sleep(0.5)

    def break_migration_lock(self) -> bool:
        """Drops a lock left by a migrator that died; True if there was one."""
        with self._lock:
            existed = bool(self.client.query(
                f"EXISTS TABLE {self.database}.{MIGRATION_LOCK}").result_rows[0][0])
            self._ddl(f"DROP TABLE IF EXISTS {self.database}.{MIGRATION_LOCK} SYNC")
            return existed

    # --- writes ---------------------------------------------------------------------

    def append(self, events: Sequence[Envelope]) -> None:
        poses, chunks, contents, metas = [], [], [], []
        for e in events:
            p = e.payload
            if isinstance(p, PoseReported):
                path = p.path or ()
                poses.append([
                    e.robot_id, e.event_time_ms,
                    _mm(p.position[0]), _mm(p.position[1]), _mm(p.position[2]),
                    *p.orientation,
                    p.battery_level, _flag(p.charging), _flag(p.loaded),
                    p.path is not None,
                    [_mm(x) for x, _ in path], [_mm(y) for _, y in path],
                    e.receive_time_ms - e.event_time_ms,
                ])
            elif isinstance(p, ChunkUpdated):
                chunks.append([e.event_time_ms, p.row, p.column, e.robot_id, p.content_hash,
                               e.receive_time_ms - e.event_time_ms])
                day = e.event_time_ms // 86_400_000
                if self._known_contents.get(p.content_hash) != day:
                    contents.append((p.content_hash, day, p.width, p.height, p.data))
            elif isinstance(p, MapMetaSet):
                metas.append([e.event_time_ms, e.robot_id, _json.encode(p.to_2019()).decode()])
        with self._lock:
            if contents:
                # Contents first: an event must never reference pixels that are not stored.
                self._insert("chunk_contents", [list(x) for x in contents],
                             ["content_hash", "day", "width", "height", "zlib_pixels"])
                for h, day, *_ in contents:
                    self._known_contents[h] = day
                if len(self._known_contents) > 1_000_000:
                    self._known_contents.clear()
            if chunks:
                self._insert("chunk_events", chunks,
                             ["ts", "row", "col", "robot_id", "content_hash", "recv_lag_ms"])
            if poses:
                self._insert("poses", poses, [
                    "robot_id", "ts", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw", "battery",
                    "charging", "loaded", "has_path", "path_x_mm", "path_y_mm", "recv_lag_ms"])
            if metas:
                self._insert("map_meta", metas, ["ts", "robot_id", "meta"])
            # A late event (at or before the newest snapshot) makes the snapshots from its
            # time on wrong. Noting that is all the batch waits for: reads stop using those
            # snapshots at once (they fold events from the last good one: exact, slower),
            # and the snapshot timer rebuilds them in bounded steps (repair_snapshots).
            times = [row[0] for row in chunks] + [row[1] for row in poses]
            if times:
                last = self._newest_snapshot()
                if last is not None and min(times) <= last:
                    self._note_repair(min(times))

    def append_dead_letters(self, records: Sequence[DeadLetter]) -> None:
        if not records:
            return
        rows = [[r.receive_time_ms, r.reason, r.mqtt_topic, r.detail, r.payload, r.gateway]
                for r in records]
        with self._lock:
            self._insert("dead_letters", rows, [
                "received", "reason", "mqtt_topic", "detail", "payload", "gateway"])

    # --- snapshots ------------------------------------------------------------------
    # A snapshot at S holds, per chunk, the winning write with event time <= S and, per
    # robot, the time of its latest pose <= S. Snapshot S is built from snapshot S - every
    # plus the events in (S - every, S], so building is cheap and reading the state at T
    # costs one snapshot plus at most `every` of events, however old T is.

    def _newest_snapshot(self) -> int | None:
        # Every batch asks; until the first snapshot exists, "none" is asked again at
        # most every few seconds instead of once per batch (~4 ms each on chDB).
        if self._last_snapshot_ms is None and time.monotonic() >= self._no_snapshot_until:
            rows = self.client.query(
                f"SELECT toUnixTimestamp64Milli(max(snap_ts)), count() "
                f"FROM {self.database}.snapshot_log").result_rows
            if rows and rows[0][1]:
                self._last_snapshot_ms = rows[0][0]
            else:
                self._no_snapshot_until = time.monotonic() + NO_SNAPSHOT_RECHECK_S
        return self._last_snapshot_ms

    def _snapshot_at_or_before(self, at_ms: int, client=None) -> int | None:
        rows = (client or self.client).query(
            f"SELECT toUnixTimestamp64Milli(max(snap_ts)), count() FROM {self.database}.snapshot_log "
            f"WHERE snap_ts <= fromUnixTimestamp64Milli({{t:Int64}}) AND snap_ts < {self._valid_before()}",
            parameters={"t": at_ms}).result_rows
        return rows[0][0] if rows and rows[0][1] else None

    def _build_one(self, snap_ms: int, prev_ms: int | None) -> None:
        db = self.database
        params = {"s": snap_ms, "p": prev_ms if prev_ms is not None else -1}
        since = "ts > fromUnixTimestamp64Milli({p:Int64}) AND " if prev_ms is not None else ""
        prev_map = (f"SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots FINAL "
                    "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) UNION ALL "
                    if prev_ms is not None else "")
        prev_robots = (f"SELECT robot_id, ts FROM {db}.robot_snapshots FINAL "
                       "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) UNION ALL "
                       if prev_ms is not None else "")
        c = self.client
        c.command(
            f"INSERT INTO {db}.map_snapshots (snap_ts, row, col, ts, robot_id, content_hash, built) "
            "SELECT fromUnixTimestamp64Milli({s:Int64}), row, col, max(ts), "
            "argMax(robot_id, (ts, robot_id)), argMax(content_hash, (ts, robot_id)), now64(3) "
            f"FROM ({prev_map}SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events "
            f"WHERE {since}ts <= fromUnixTimestamp64Milli({{s:Int64}})) GROUP BY row, col",
            parameters=params)
        c.command(
            f"INSERT INTO {db}.robot_snapshots (snap_ts, robot_id, ts, built) "
            "SELECT fromUnixTimestamp64Milli({s:Int64}), robot_id, max(ts), now64(3) "
            f"FROM ({prev_robots}SELECT robot_id, ts FROM {db}.poses "
            f"WHERE {since}ts <= fromUnixTimestamp64Milli({{s:Int64}})) GROUP BY robot_id",
            parameters=params)
        c.command(
            f"INSERT INTO {db}.snapshot_log (snap_ts, built, chunks, robots) "
            "SELECT fromUnixTimestamp64Milli({s:Int64}), now64(3), "
            f"(SELECT count() FROM {db}.map_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({{s:Int64}})), "
            f"(SELECT count() FROM {db}.robot_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({{s:Int64}}))",
            parameters=params)

    def _note_repair(self, from_ms: int) -> None:
        self._insert("snapshot_repairs", [[from_ms, time.time_ns() // 1_000_000]],
                     ["from_ts", "noted"])

    def _valid_before(self) -> str:
        """SQL for the first instant whose snapshots may be wrong (a pending repair's
        start), or far in the future: reads use only snapshots before it."""
        return (f"(SELECT ifNull(toDateTime64(min(from_ts), 3, 'UTC'), "
                f"toDateTime64('2299-12-31 00:00:00', 3, 'UTC')) FROM {self.database}.snapshot_repairs)")

    def repair_snapshots(self, max_snapshots: int = 144) -> int:
        """Rebuilds at most `max_snapshots` of the snapshots a late event invalidated,
        oldest first, in one bulk statement per table; returns how many. The snapshot
        timer calls it until nothing is pending, so a late event costs the consumer no
        time and the repair is spread over ticks."""
        db, every = self.database, self.snapshot_every_ms
        with self._lock:
            rows = self.client.query(
                f"SELECT toUnixTimestamp64Milli(min(from_ts)), count(), "
                f"toUnixTimestamp64Milli(max(noted)) FROM {db}.snapshot_repairs").result_rows
            if not rows or not rows[0][1]:
                return 0
            from_ms, _, noted_ms = rows[0]
            newest = self._newest_snapshot()
            first = -(-from_ms // every) * every  # the first snapshot that can contain from_ms
            if newest is None or first > newest:
                self.client.command(f"DELETE FROM {db}.snapshot_repairs WHERE noted <= "
                                    "fromUnixTimestamp64Milli({n:Int64})", parameters={"n": noted_ms})
                return 0
            last = min(newest, first + (max_snapshots - 1) * every)
            prev = first - every
            self._build_run(first, last, prev if self._has_snapshot(prev) else None)
            # Done up to `last`: what was noted before this step now starts after it (a
            # late event noted meanwhile keeps its own, earlier row).
            if last < newest:
                self._insert("snapshot_repairs", [[last + 1, noted_ms]], ["from_ts", "noted"])
            self.client.command(
                f"DELETE FROM {db}.snapshot_repairs WHERE noted <= fromUnixTimestamp64Milli({{n:Int64}}) "
                "AND from_ts <= fromUnixTimestamp64Milli({l:Int64})",
                parameters={"n": noted_ms, "l": last})
            return (last - first) // every + 1

    def _has_snapshot(self, snap_ms: int) -> bool:
        return bool(self.client.query(
            f"SELECT count() FROM {self.database}.snapshot_log WHERE snap_ts = "
            "fromUnixTimestamp64Milli({s:Int64})", parameters={"s": snap_ms}).result_rows[0][0])

    def build_snapshots(self, up_to_ms: int) -> int:
        """Builds every grid snapshot up to `up_to_ms` not built yet; returns how many."""
        every = self.snapshot_every_ms
        with self._lock:
            last = self._newest_snapshot()
            if last is None:
                rows = self.client.query(
                    "SELECT toUnixTimestamp64Milli(min(ts)), count() FROM ("
                    f"SELECT ts FROM {self.database}.chunk_events UNION ALL "
                    f"SELECT ts FROM {self.database}.poses)").result_rows
                if not rows[0][1]:
                    return 0
                # The first snapshot folds everything before it; each later one one interval.
                oldest = max(rows[0][0], up_to_ms - self.retention_days * 86_400_000)
                first = oldest // every * every
                snaps = list(range(first, up_to_ms + 1, every))
                prev = None
            else:
                snaps = list(range(last + every, up_to_ms + 1, every))
                prev = last
            for snap in snaps:
                self._build_one(snap, prev)
                prev = snap
                self._last_snapshot_ms = snap
            return len(snaps)

    def _due_snapshots(self, up_to_ms: int) -> tuple[list[int], int | None]:
        """The snapshots build_snapshots(up_to_ms) would build, and the one before them."""
        every = self.snapshot_every_ms
        last = self._newest_snapshot()
        if last is not None:
            return list(range(last + every, up_to_ms + 1, every)), last
        rows = self.client.query(
            "SELECT toUnixTimestamp64Milli(min(ts)), count() FROM ("
            f"SELECT ts FROM {self.database}.chunk_events UNION ALL "
            f"SELECT ts FROM {self.database}.poses)").result_rows
        if not rows[0][1]:
            return [], None
        oldest = max(rows[0][0], up_to_ms - self.retention_days * 86_400_000)
        return list(range(oldest // every * every, up_to_ms + 1, every)), None

    def build_snapshots_bulk(self, up_to_ms: int, per_query: int = 144,
                             on_progress: Callable[[int, int], None] | None = None) -> int:
        """build_snapshots(up_to_ms), `per_query` snapshots per statement: the same rows.

        For a run of snapshots S1 < ... < Sn following snapshot P (or none): each write
        with P < t <= Sn (or any t <= Sn without P) falls in the bucket of the first
        snapshot at or after it (S1 for everything older), P's rows in bucket P; the
        winners per bucket and chunk (robot) are then carried forward to every later
        snapshot with an ASOF JOIN. That is what the chain of `_build_one` computes, one
        statement per table and run instead of three per snapshot.
        """
        with self._lock:
            snaps, prev = self._due_snapshots(up_to_ms)
            for i in range(0, len(snaps), per_query):
                run = snaps[i:i + per_query]
                self._build_run(run[0], run[-1], prev)
                prev = run[-1]
                self._last_snapshot_ms = prev
                if on_progress is not None:
                    on_progress(i + len(run), len(snaps))
            return len(snaps)

    def _build_run(self, first_ms: int, last_ms: int, prev_ms: int | None) -> None:
        db, every = self.database, self.snapshot_every_ms
        params = {"a": first_ms, "b": last_ms, "e": every, "p": prev_ms if prev_ms is not None else -1}
        since = "ts > fromUnixTimestamp64Milli({p:Int64}) AND " if prev_ms is not None else ""
        bucket = ("greatest({a:Int64}, intDiv(toUnixTimestamp64Milli(ts) + {e:Int64} - 1, "
                  "{e:Int64}) * {e:Int64})")
        snap_times = "arrayJoin(range({a:Int64}, {b:Int64} + 1, {e:Int64}))"
        prev_map = (f"SELECT {{p:Int64}} AS bucket, row, col, ts, robot_id, content_hash "
                    f"FROM {db}.map_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({{p:Int64}}) "
                    "UNION ALL " if prev_ms is not None else "")
        prev_robots = (f"SELECT {{p:Int64}} AS bucket, robot_id, ts FROM {db}.robot_snapshots FINAL "
                       "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) UNION ALL "
                       if prev_ms is not None else "")
        c = self.client
        c.command(
            f"INSERT INTO {db}.map_snapshots (snap_ts, row, col, ts, robot_id, content_hash, built) "
            "WITH w AS (SELECT bucket, row, col, max(ts) AS win_ts, "
            "argMax(robot_id, (ts, robot_id)) AS win_robot, "
            "argMax(content_hash, (ts, robot_id)) AS win_hash "
            f"FROM ({prev_map}SELECT {bucket} AS bucket, row, col, ts, robot_id, content_hash "
            f"FROM {db}.chunk_events WHERE {since}ts <= fromUnixTimestamp64Milli({{b:Int64}})) "
            "GROUP BY bucket, row, col) "
            "SELECT fromUnixTimestamp64Milli(g.snap), g.row, g.col, w.win_ts, w.win_robot, "
            "w.win_hash, now64(3) "
            f"FROM (SELECT {snap_times} AS snap, row, col FROM (SELECT DISTINCT row, col FROM w)) AS g "
            "ASOF JOIN w ON g.row = w.row AND g.col = w.col AND g.snap >= w.bucket",
            parameters=params)
        c.command(
            f"INSERT INTO {db}.robot_snapshots (snap_ts, robot_id, ts, built) "
            "WITH w AS (SELECT bucket, robot_id, max(ts) AS win_ts "
            f"FROM ({prev_robots}SELECT {bucket} AS bucket, robot_id, ts FROM {db}.poses "
            f"WHERE {since}ts <= fromUnixTimestamp64Milli({{b:Int64}})) GROUP BY bucket, robot_id) "
            "SELECT fromUnixTimestamp64Milli(g.snap), g.robot_id, w.win_ts, now64(3) "
            f"FROM (SELECT {snap_times} AS snap, robot_id FROM (SELECT DISTINCT robot_id FROM w)) AS g "
            "ASOF JOIN w ON g.robot_id = w.robot_id AND g.snap >= w.bucket",
            parameters=params)
        window = ("snap_ts >= fromUnixTimestamp64Milli({a:Int64}) AND "
                  "snap_ts <= fromUnixTimestamp64Milli({b:Int64})")
        c.command(
            f"INSERT INTO {db}.snapshot_log (snap_ts, built, chunks, robots) "
            "SELECT fromUnixTimestamp64Milli(g.snap), now64(3), m.n, r.n "
            f"FROM (SELECT {snap_times} AS snap) AS g "
            "LEFT JOIN (SELECT toUnixTimestamp64Milli(snap_ts) AS snap, count() AS n "
            f"FROM {db}.map_snapshots FINAL WHERE {window} GROUP BY snap_ts) AS m ON g.snap = m.snap "
            "LEFT JOIN (SELECT toUnixTimestamp64Milli(snap_ts) AS snap, count() AS n "
            f"FROM {db}.robot_snapshots FINAL WHERE {window} GROUP BY snap_ts) AS r ON g.snap = r.snap",
            parameters=params)

    # --- conflicts ------------------------------------------------------------------

    def chunk_writes_near(self, chunks: Sequence[tuple[int, int]], from_ms: int,
                          to_ms: int) -> list[ChunkRow]:
        if not chunks:
            return []
        rows = self._rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts <= fromUnixTimestamp64Milli({t:Int64}) "
            "WHERE (row, col) IN (SELECT tupleElement(c, 1), tupleElement(c, 2) "
            "FROM (SELECT arrayJoin({cs:Array(Tuple(UInt16, UInt16))}) AS c)) "
            f"ORDER BY ts, row, col, robot_id {_FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "cs": [tuple(c) for c in set(chunks)]},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def append_conflicts(self, rows: Sequence[ConflictRow]) -> None:
        if not rows:
            return
        data = [[c.ts_ms, c.row, c.column, c.robot_b, c.robot_a, c.ts_a_ms] for c in rows]
        with self._lock:
            self._insert("conflicts", data, [
                "ts", "row", "col", "robot_b", "robot_a", "ts_a"])

    def conflicts(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ConflictRow]:
        rows = self._rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_a, toUnixTimestamp64Milli(ts_a), "
            f"robot_b FROM {self.database}.conflicts FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_b LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ConflictRow(*r) for r in rows]

    def conflict_counts(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        if bucket_ms <= 0:
            raise ValueError("bucket_ms must be positive")
        # Without FINAL: count distinct identities, the same number FINAL would give.
        rows = self._rows(
            "SELECT {f:Int64} + intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {b:Int64}) * {b:Int64} "
            "AS start, uniqExact(ts, row, col, robot_b) "
            f"FROM {self.database}.conflicts "
            "WHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "GROUP BY start ORDER BY start",
            {"f": from_ms, "t": to_ms, "b": bucket_ms},
        )
        return {int(start): int(n) for start, n in rows}

    # --- reads ----------------------------------------------------------------------

    def _rows(self, sql: str, params: dict, **query_options) -> list[tuple]:
        with self._reader() as c:
            return c.query(sql, parameters=params, **query_options).result_rows

    def _pose_query(self, sql: str, params: dict) -> list[PoseRow]:
        with self._reader() as c:
            columns = c.query(sql, parameters=params).result_columns
        return _pose_rows(columns)

    def poses(self, from_ms: int, to_ms: int, robot_id: str | None = None,
              limit: int = 100_000) -> list[PoseRow]:
        # PREWHERE on sorting-key columns only: duplicates of one identity pass or fail
        # together, so FINAL still sees all of them; the other columns are read only for
        # granules holding rows of the window.
        where = "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        params: dict = {"f": from_ms, "t": to_ms, "n": limit}
        if robot_id is not None:
            where += " AND robot_id = {r:String}"
            params["r"] = robot_id
        return self._pose_query(
            f"SELECT {_POSE_COLUMNS} FROM {self.database}.poses FINAL PREWHERE {where} "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            params,
        )

    def poses_downsampled(self, from_ms: int, to_ms: int, step_ms: int,
                          robot_id: str | None = None, limit: int = 100_000) -> list[PoseRow]:
        """Per robot and step bucket [from + k*step, from + (k+1)*step), its first pose in
        from_ms <= event time < to_ms; ordered by time then robot, like poses()."""
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        where = "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        params: dict = {"f": from_ms, "t": to_ms, "s": step_ms, "n": limit}
        if robot_id is not None:
            where += " AND robot_id = {r:String}"
            params["r"] = robot_id
        aligned = from_ms % KEYFRAME_MS == 0 and step_ms % KEYFRAME_MS == 0
        if aligned or step_ms >= 10 * KEYFRAME_MS:
            return self._pose_query(self._keyframe_sql(aligned, robot_id), params)
        return self._pose_query(
            f"SELECT {_POSE_COLUMNS} FROM (SELECT * FROM {self.database}.poses FINAL WHERE {where} "
            "ORDER BY robot_id, ts "
            "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            params,
        )

    def _keyframe_sql(self, aligned: bool, robot_id: str | None) -> str:
        """poses_downsampled from the per-minute keyframes (schema v4), exactly.

        A step [b, b + step) is a head [b, next whole minute), then minutes starting in it.
        Its first pose is either in the head, or the first pose of the first of those
        minutes holding one in the step, i.e. that minute's keyframe (a minute cut by the
        step's end counts only if its keyframe is before the end). So the candidates are
        the keyframes in the window plus every pose in the heads, read from `poses`: none
        when `from` and the step are whole minutes, a minute per step at most otherwise
        (steps of 10 min or more, so at most a tenth of the window; only the time column
        of the rest is read, to find them).
        """
        db = self.database
        robot = " AND robot_id = {r:String}" if robot_id is not None else ""
        window = ("ts >= fromUnixTimestamp64Milli({f:Int64}) "
                  "AND ts < fromUnixTimestamp64Milli({t:Int64})")
        candidates = (
            f"SELECT {POSE_COLUMNS} FROM {db}.pose_keyframes FINAL "
            "PREWHERE cell >= toStartOfMinute(fromUnixTimestamp64Milli({f:Int64})) "
            f"AND cell < fromUnixTimestamp64Milli({{t:Int64}}){robot} WHERE {window}")
        if not aligned:
            # The head of the step a pose falls in ends at the minute after the step's start.
            start = ("({f:Int64} + intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64}) "
                     "* {s:Int64})")
            candidates += (
                f" UNION ALL SELECT {POSE_COLUMNS} FROM {db}.poses FINAL PREWHERE {window}{robot} "
                f"AND toUnixTimestamp64Milli(ts) < intDiv({start} + {KEYFRAME_MS - 1}, "
                f"{KEYFRAME_MS}) * {KEYFRAME_MS}")
        return (f"SELECT {_POSE_COLUMNS} FROM (SELECT * FROM ({candidates}) ORDER BY robot_id, ts "
                "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
                f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}")

    def map_at(self, at_ms: int) -> list[ChunkState]:
        """Every chunk's winning write at or before `at_ms` (nearest snapshot + events).

        One statement: the nearest snapshot's time is a scalar subquery (ClickHouse folds
        it to a constant before choosing granules). Without a snapshot it is the epoch, so
        the snapshot side is empty and every event <= `at_ms` is folded.
        """
        db = self.database
        with self._reader() as c:
            rows = c.query(
                f"WITH (SELECT max(snap_ts) FROM {db}.snapshot_log "
                "WHERE snap_ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"AND snap_ts < {self._valid_before()}) AS snap "
                "SELECT row, col, toUnixTimestamp64Milli(max(ts)), argMax(robot_id, (ts, robot_id)), "
                "lower(hex(argMax(content_hash, (ts, robot_id)))) "
                f"FROM (SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots "
                "WHERE snap_ts = snap UNION ALL "
                f"SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events "
                "WHERE ts > snap AND ts <= fromUnixTimestamp64Milli({t:Int64})) "
                "GROUP BY row, col ORDER BY row, col", parameters={"t": at_ms}).result_rows
        return [ChunkState(*r) for r in rows]

    def robots_at(self, at_ms: int) -> list[PoseRow]:
        """Each robot's latest pose at or before `at_ms` (nearest snapshot + events).

        A robot that reported in (snapshot, at_ms] is answered by one pass over those poses
        (its latest there is its latest <= at_ms); only robots silent since the snapshot
        need the snapshot's time of their last pose and a lookup of that row.
        """
        db = self.database
        with self._reader() as c:
            # The nearest snapshot and its robots (max(ts): a rebuilt snapshot may still
            # hold its older rows until merged).
            listed = c.query(
                f"WITH (SELECT max(snap_ts) FROM {db}.snapshot_log "
                "WHERE snap_ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"AND snap_ts < {self._valid_before()}) AS snap "
                "SELECT toUnixTimestamp64Milli(any(snap)), robot_id "
                f"FROM {db}.robot_snapshots WHERE snap_ts = snap GROUP BY robot_id",
                parameters={"t": at_ms}).result_rows
            snap = listed[0][0] if listed else self._snapshot_at_or_before(at_ms, c)
            if snap is None:
                columns = c.query(
                    f"SELECT {_POSE_COLUMNS} FROM {db}.poses FINAL WHERE (robot_id, ts) IN ("
                    f"SELECT robot_id, max(ts) FROM {db}.poses "
                    "WHERE ts <= fromUnixTimestamp64Milli({t:Int64}) GROUP BY robot_id) "
                    f"ORDER BY robot_id {_FINAL_SETTINGS}", parameters={"t": at_ms}).result_columns
                return _pose_rows(columns)
            params: dict = {"t": at_ms, "p": snap}
            recent = _pose_rows(c.query(
                f"SELECT {_POSE_COLUMNS} FROM {db}.poses FINAL "
                "PREWHERE ts > fromUnixTimestamp64Milli({p:Int64}) "
                "AND ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"ORDER BY robot_id, ts DESC LIMIT 1 BY robot_id {_FINAL_SETTINGS}",
                parameters=params).result_columns)
            seen = {r.robot_id for r in recent}
            params["silent"] = [robot for _, robot in listed if robot not in seen]
            if not params["silent"]:
                return recent  # ordered by robot id
            silent = _pose_rows(c.query(
                f"SELECT {_POSE_COLUMNS} FROM {db}.poses FINAL WHERE (robot_id, ts) IN ("
                f"SELECT robot_id, max(ts) FROM {db}.robot_snapshots "
                "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) "
                "AND has({silent:Array(String)}, robot_id) GROUP BY robot_id) "
                f"{_FINAL_SETTINGS}", parameters=params).result_columns)
        return sorted(recent + silent, key=lambda r: r.robot_id)

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        # PREWHERE on the sorting key's `ts`: as in poses(), FINAL sees every duplicate.
        rows = self._rows(
            f"SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def timeline(self, from_ms: int, to_ms: int, buckets: int) -> list[TimelineBucket]:
        bucket_ms, starts = timeline_buckets(from_ms, to_ms, buckets)
        if not starts:
            return []
        db = self.database
        params = {"f": from_ms, "t": to_ms, "b": bucket_ms}
        window = ("ts >= fromUnixTimestamp64Milli({f:Int64}) "
                  "AND ts < fromUnixTimestamp64Milli({t:Int64})")
        bucket = "intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {b:Int64})"
        chunks = dict(self._rows(
            f"SELECT {bucket} AS k, count() FROM {db}.chunk_events FINAL PREWHERE {window} "
            f"GROUP BY k {_FINAL_SETTINGS}", params))
        if from_ms % KEYFRAME_MS == 0 and bucket_ms % KEYFRAME_MS == 0:
            # Buckets of whole minutes: a robot has a pose in a bucket iff it has a
            # keyframe (its first pose of a minute) there.
            robots = dict(self._rows(
                f"SELECT {bucket} AS k, uniqExact(robot_id) FROM {db}.pose_keyframes FINAL "
                "PREWHERE cell >= fromUnixTimestamp64Milli({f:Int64}) "
                "AND cell < fromUnixTimestamp64Milli({t:Int64}) "
                f"WHERE ts < fromUnixTimestamp64Milli({{t:Int64}}) GROUP BY k {_FINAL_SETTINGS}",
                params))
        else:  # a duplicate pose names the same robot: no FINAL needed
            robots = dict(self._rows(
                f"SELECT {bucket} AS k, uniqExact(robot_id) FROM {db}.poses PREWHERE {window} "
                "GROUP BY k", params))
        conflicts = self.conflict_counts(from_ms, to_ms, bucket_ms)
        return [TimelineBucket(start, chunks.get(k, 0), conflicts.get(start, 0), robots.get(k, 0))
                for k, start in enumerate(starts)]

    def robot_known(self, robot_id: str) -> bool:
        # pose_keyframes is sorted by robot: a primary-key lookup, not a scan of `poses`.
        return bool(self._rows(
            f"SELECT 1 FROM {self.database}.pose_keyframes WHERE robot_id = {{r:String}} LIMIT 1",
            {"r": robot_id}))

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        rows = self._rows(
            f"SELECT width, height, zlib_pixels FROM {self.database}.chunk_contents "
            "WHERE content_hash = unhex({h:String}) LIMIT 1",
            {"h": content_hash.hex()},
            # As bytes: read as text, zlib data that is not UTF-8 would come back as hex.
            column_formats={"zlib_pixels": "bytes"},
        )
        if not rows:
            return None
        w, h, data = rows[0]
        return w, h, bytes(data)

    def chunk_contents(self, hashes: Sequence[bytes]) -> dict[bytes, tuple[int, int, bytes]]:
        """Many content hashes at once: hash -> (width, height, zlib pixels)."""
        if not hashes:
            return {}
        rows = self._rows(
            f"SELECT content_hash, any(width), any(height), any(zlib_pixels) "
            f"FROM {self.database}.chunk_contents WHERE content_hash IN "
            "(SELECT arrayJoin(arrayMap(h -> toFixedString(unhex(h), 16), {hs:Array(String)}))) "
            "GROUP BY content_hash",
            {"hs": [h.hex() for h in set(hashes)]},
            column_formats={"content_hash": "bytes", "any(zlib_pixels)": "bytes"},
        )
        return {bytes(h): (w, ht, bytes(d)) for h, w, ht, d in rows}

    def latest_meta(self) -> MapMetaSet | None:
        rows = self._rows(
            f"SELECT meta FROM {self.database}.map_meta FINAL ORDER BY ts DESC LIMIT 1", {})
        if not rows:
            return None
        doc = msgspec.json.decode(rows[0][0])
        return MapMetaSet.from_2019(doc)

    # --- the 2019 REST contract ----------------------------------------------------------

    def list_chunks(self, query: ChunkQuery) -> list[ChunkRow]:
        rows = self._legacy_rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.database}.chunk_events FINAL", query,
            lambda sql, params: self._rows(sql, params))
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def list_poses(self, query: PoseQuery) -> list[PoseRow]:
        return self._legacy_rows(
            f"SELECT {_POSE_COLUMNS} FROM {self.database}.poses FINAL", query, self._pose_query)

    def _legacy_rows(self, select: str, query: ChunkQuery | PoseQuery, run: Callable) -> list:
        """Filters only on sorting-key columns (PREWHERE keeps FINAL exact, as in poses()),
        the order from the whitelist (never the client's text), LIMIT/OFFSET as bound
        parameters. A newest-first read without a lower bound first tries the last hour,
        then day: when that window alone fills skip + limit, the answer is the same."""
        where = []
        params: dict = {"n": query.limit, "s": query.skip}
        for column, op, value in (("ts", "=", query.timestamp_ms),
                                  ("ts", ">=", query.updated_since_ms),
                                  ("ts", "<", query.updated_before_ms)):
            if value is not None:
                name = f"p{len(params)}"
                where.append(f"{column} {op} fromUnixTimestamp64Milli({{{name}:Int64}})")
                params[name] = value
        if query.robot_id is not None:
            where.append("robot_id = {robot:String}")
            params["robot"] = query.robot_id
        if isinstance(query, ChunkQuery):
            for column, value in (("row", query.row), ("col", query.column)):
                if value is not None:
                    where.append(f"{column} = {{{column}:UInt16}}")
                    params[column] = value
        order = ", ".join(f"{sort_column(f)} {'DESC' if d == 'desc' else 'ASC'}"
                          for f, d in query.order)

        def sql(extra: list[str]) -> str:
            clause = f" PREWHERE {' AND '.join(where + extra)}" if where or extra else ""
            return (f"{select}{clause} ORDER BY {order} LIMIT {{n:UInt32}} OFFSET {{s:UInt32}} "
                    f"{_FINAL_SETTINGS}")

        if (query.limit and query.order[0] == ("timestamp", "desc")
                and query.updated_since_ms is None and query.timestamp_ms is None):
            upper = query.updated_before_ms or time.time_ns() // 1_000_000
            for span_ms in (3_600_000, 86_400_000):
                rows = run(sql(["ts >= fromUnixTimestamp64Milli({lower:Int64})"]),
                           {**params, "lower": upper - span_ms})
                if len(rows) == query.limit:
                    return rows
        return run(sql([]), params)

    def delete_chunks(self) -> int:
        db = self.database
        with self._lock:
            (removed,), = self._rows(f"SELECT count() FROM {db}.chunk_events FINAL", {})
            # TRUNCATE, not a lightweight DELETE: the whole table goes, at once and without
            # a mutation. Snapshots go too, or map_at would still answer with deleted
            # writes; their log stays, so the next snapshot builds on an empty map.
            self.client.command(f"TRUNCATE TABLE {db}.chunk_events")
            self.client.command(f"TRUNCATE TABLE {db}.map_snapshots")
            self.client.command(f"TRUNCATE TABLE IF EXISTS {db}.conflicts")  # derived from them
        return int(removed)

    def delete_meta(self) -> int:
        db = self.database
        with self._lock:
            (removed,), = self._rows(f"SELECT count() FROM {db}.map_meta FINAL", {})
            self.client.command(f"TRUNCATE TABLE {db}.map_meta")
        return int(removed)

    def counts(self) -> Counts:
        db = self.database
        (row,) = self._rows(
            f"SELECT (SELECT count() FROM {db}.poses FINAL), "
            f"(SELECT count() FROM {db}.chunk_events FINAL), "
            f"(SELECT uniqExact(content_hash) FROM {db}.chunk_contents), "
            f"(SELECT count() FROM {db}.dead_letters)", {})
        return Counts(*row)

    def storage_bytes(self) -> dict[str, int]:
        """Bytes on disk per table (active parts), for benchmarks and operators."""
        rows = self._rows(
            "SELECT table, sum(bytes_on_disk) FROM system.parts WHERE database = {d:String} "
            "AND active GROUP BY table", {"d": self.database})
        return {t: int(b) for t, b in rows}

    def optimize(self) -> None:
        """Merges parts now (and drops duplicates); benchmarks call it before measuring."""
        with self._lock:
            for table in ("poses", "chunk_events", "chunk_contents", "map_meta", "dead_letters",
                          "pose_keyframes"):
                self.client.command(f"OPTIMIZE TABLE {self.database}.{table} FINAL")

    def ping(self, timeout_s: float = 2.0) -> bool:
        """A real round trip to ClickHouse on a client of its own (a hung server must not
        hold the read or write client); readiness calls it through a CachedCheck."""
        if self._ping_client is None:
            if self.dsn.startswith("chdb://"):
                self._ping_client = self._connect()
            else:
                self._ping_client = clickhouse_connect.get_client(
                    dsn=self.dsn, username=self._username, password=self._password,
                    connect_timeout=timeout_s, send_receive_timeout=timeout_s, **self.tls)
        return self._ping_client.command("SELECT 1") == 1

    def export_query(self, sql: str, parameters: dict, fmt: str) -> bytes:
        """A read's result as ClickHouse writes it in `fmt` (CSVWithNames, Parquet, ...);
        mapservice/adapters/exports.py builds `sql` from fixed names, values go as parameters."""
        with self._reader() as client:
            return client.raw_query(sql, parameters=parameters, fmt=fmt)

    def close(self) -> None:
        with self._lock, self._read_lock:
            for client in (self._client, self._read_client):
                if client is not None:
                    client.close()
            self._client = self._read_client = None

