"""The store's retention step: history older than the retention goes, the state it built
stays.

The service owns expiry (schema v11 removed every ClickHouse TTL: it follows the server's
real clock and dropped the only writes of a floor unchanged for a week). One step, run by
the processors' snapshot timer on the service's clock (`adapters/clock.py`):

1. The anchor: the newest valid snapshot at or before `now - retention` (built first if
   the snapshot timer has not got there). It holds every chunk's winning write up to its
   instant and each robot's latest pose time: the floor, however old its writes are.
2. The cut: the anchor's day. Day partitions before it can go, since every instant from
   the anchor on is the anchor plus the events after it (kept: they are in its day or
   later). Retention is therefore kept to the day: between `retention` and `retention +
   a day` of history stays.
3. Contents named by any row that stays (a kept snapshot or a kept chunk write) whose
   pixels live only in a partition about to go are copied into today's partition first:
   pixels live as long as any retained row names them, renewed once per retention period
   while a snapshot still carries them (the floor: a few hundred chunks a week).
4. The day partitions before the cut are dropped from every day-partitioned table; the
   snapshot log forgets the snapshots whose rows went; map metadata superseded before the
   boundary goes, the one in force at the boundary stays.
5. Operators' annotations are state: of their edits before the boundary only those that
   make the annotations standing at the boundary stay (each one's latest edit and its
   creation); a removed annotation's edits go. The edits after the boundary are history.

Storage is then flat per day after the first retention period: the kept days, plus the
renewed floor. `ClickHouseRetention` (the RetentionKeeper role) holds the connection and the
store's `snapshots.ClickHouseSnapshots` (it builds the anchor when missing).
"""

from __future__ import annotations

import datetime as dt

import structlog

from mapservice.adapters.clickhouse.annotation_reads import edit_of
from mapservice.adapters.clickhouse.cluster import for_cluster
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.adapters.clickhouse.schema import RETAINED_BY_DAY
from mapservice.adapters.clickhouse.snapshots import ClickHouseSnapshots
from mapservice.core.annotations import prune_before
from mapservice.core.ports import RetentionResult
from mapservice.core.retention import DAY_MS

log = structlog.get_logger(__name__)


class ClickHouseRetention:
    """apply_retention: expiry by the service's clock, the floor carried forward."""

    def __init__(self, connection: ClickHouseConnection, snapshots: ClickHouseSnapshots) -> None:
        self.connection = connection
        self.snapshots = snapshots

    def apply_retention(self, now_ms: int) -> RetentionResult:
        """Drops the history older than the retention at `now_ms` (day partitions before
        the day of the anchor snapshot), keeping the state at every instant from
        `now_ms - retention` on exact: the floor, its pixels, the map metadata."""
        boundary = now_ms - self.connection.retention_days * DAY_MS
        db = self.connection.database
        with self.connection.lock:
            self._prune_annotation_edits(boundary)
            anchor = self._retention_anchor(boundary)
            if anchor is None:
                return RetentionResult(None, None, 0, 0)
            cut = dt.date(1970, 1, 1) + dt.timedelta(days=anchor // DAY_MS)
            cut_id = cut.strftime("%Y%m%d")
            old = self._rows_w(
                "SELECT table, partition_id FROM system.parts WHERE database = {d:String} "
                "AND active AND has(splitByChar(',', {t:String}), table) "
                "AND partition_id < {c:String} GROUP BY table, partition_id ORDER BY table, partition_id",
                {"d": db, "t": ",".join(RETAINED_BY_DAY), "c": cut_id},
            )
            renewed = 0
            if any(table == "chunk_contents" for table, _ in old):
                renewed = self._renew_contents(cut, now_ms)
            if any(table == "poses" for table, _ in old):
                self._carry_poses(anchor, cut)
            for table, partition in old:
                self.connection.client.command(
                    for_cluster(
                        f"ALTER TABLE {db}.{table} DROP PARTITION ID '{partition}'",
                        self.connection.cluster,
                    )
                )
            if old:
                self.connection.client.command(
                    f"DELETE FROM {db}.snapshot_log WHERE snap_ts < toDateTime64({{c:Date}}, 3, 'UTC')",
                    parameters={"c": cut},
                )
                self._drop_superseded_meta(boundary)
                log.info(
                    "retention applied",
                    anchor_ms=anchor,
                    first_day_kept=str(cut),
                    partitions_dropped=len(old),
                    contents_renewed=renewed,
                )
            return RetentionResult(anchor, cut.isoformat(), len(old), renewed)

    def _rows_w(self, sql: str, params: dict) -> list:
        return self.connection.client.query(sql, parameters=params).result_rows

    def _retention_anchor(self, boundary_ms: int) -> int | None:
        """The newest valid snapshot at or before the boundary, built if missing."""
        for attempt in range(2):
            rows = self._rows_w(
                f"SELECT toUnixTimestamp64Milli(max(snap_ts)), count() FROM {self.connection.database}.snapshot_log "
                "WHERE snap_ts <= fromUnixTimestamp64Milli({b:Int64}) "
                f"AND snap_ts < {self.connection.valid_before()}",
                {"b": boundary_ms},
            )
            if rows and rows[0][1]:
                return int(rows[0][0])
            if attempt == 0:
                # The snapshot timer builds them; on a store that was down (or a first
                # start on old history) the boundary may be ahead of them.
                self.snapshots.build_snapshots(boundary_ms)
        return None

    def _renew_contents(self, cut: dt.date, now_ms: int) -> int:
        """Copies into today's partition the contents that a kept row names and that only
        partitions before `cut` hold; returns how many."""
        db = self.connection.database
        today = dt.date(1970, 1, 1) + dt.timedelta(days=now_ms // DAY_MS)
        kept_from = "toDateTime64({c:Date}, 3, 'UTC')"
        named = (
            f"SELECT content_hash FROM {db}.map_snapshots WHERE snap_ts >= {kept_from} "
            f"UNION DISTINCT SELECT content_hash FROM {db}.chunk_events WHERE ts >= {kept_from}"
        )
        params = {"c": cut, "today": today}
        ((count,),) = self._rows_w(
            f"SELECT uniqExact(content_hash) FROM {db}.chunk_contents WHERE day < {{c:Date}} "
            f"AND content_hash IN ({named}) AND content_hash NOT IN "
            f"(SELECT content_hash FROM {db}.chunk_contents WHERE day >= {{c:Date}})",
            params,
        )
        if count:
            self.connection.client.command(
                f"INSERT INTO {db}.chunk_contents (content_hash, day, width, height, zlib_pixels) "
                "SELECT content_hash, {today:Date}, any(width), any(height), any(zlib_pixels) "
                f"FROM {db}.chunk_contents WHERE day < {{c:Date}} AND content_hash IN ({named}) "
                f"AND content_hash NOT IN (SELECT content_hash FROM {db}.chunk_contents "
                "WHERE day >= {c:Date}) GROUP BY content_hash",
                parameters=params,
            )
            self.connection.known_contents.clear()  # days it remembers may be the dropped ones
        return int(count)

    def _carry_poses(self, anchor_ms: int, cut: dt.date) -> None:
        """Carries the poses the anchor snapshot names that are older than the cut: each
        robot's last pose, however long it has been silent (one row per robot: the newer
        carried pose replaces the older, merged at once, the table holding a row a robot)."""
        db = self.connection.database
        self.connection.client.command(
            f"INSERT INTO {db}.carried_poses SELECT * FROM {db}.poses FINAL "
            "WHERE ts < toDateTime64({c:Date}, 3, 'UTC') AND (robot_id, ts) IN "
            f"(SELECT robot_id, ts FROM {db}.robot_snapshots "
            "WHERE snap_ts = fromUnixTimestamp64Milli({a:Int64}))",
            parameters={"a": anchor_ms, "c": cut},
        )
        self.connection.client.command(f"OPTIMIZE TABLE {db}.carried_poses FINAL")

    def _prune_annotation_edits(self, boundary_ms: int) -> None:
        """Deletes the annotation edits before the boundary that no annotation standing at
        the boundary needs (its latest edit, and its creation, stay however old)."""
        db = self.connection.database
        # The same rule as the memory store's (core `prune_before`), on the edits up to the
        # boundary: a few per annotation once pruned, so reading them is cheap.
        rows = self._rows_w(
            f"SELECT toUnixTimestamp64Milli(ts), event_id, change, annotation_id, author, body "
            f"FROM {db}.annotation_events FINAL WHERE ts <= fromUnixTimestamp64Milli({{b:Int64}})",
            {"b": boundary_ms},
        )
        edits = [edit_of(r, check=False) for r in rows]
        kept = {e.event_id for e in prune_before(edits, boundary_ms)}
        gone = sorted({e.event_id for e in edits if e.ts_ms < boundary_ms} - kept)
        if gone:
            self.connection.client.command(
                f"DELETE FROM {db}.annotation_events WHERE ts < fromUnixTimestamp64Milli({{b:Int64}}) "
                "AND has({ids:Array(String)}, event_id)",
                parameters={"b": boundary_ms, "ids": gone},
            )
            log.info("annotation edits before the retention pruned", edits=len(gone))

    def _drop_superseded_meta(self, boundary_ms: int) -> None:
        """Map metadata replaced before the boundary: the one in force at the boundary stays."""
        db = self.connection.database
        rows = self._rows_w(
            f"SELECT toUnixTimestamp64Milli(max(ts)), count() FROM {db}.map_meta "
            "WHERE ts <= fromUnixTimestamp64Milli({b:Int64})",
            {"b": boundary_ms},
        )
        if rows and rows[0][1]:
            self.connection.client.command(
                f"DELETE FROM {db}.map_meta WHERE ts < fromUnixTimestamp64Milli({{m:Int64}})",
                parameters={"m": int(rows[0][0])},
            )
