"""The store's change feed, newest first in time slices (mapservice/core/change_scan.py):
each slice's chunk writes (with the margin the upload rule needs) and, for chunks first
written inside a slice, the content they had before; the rule itself (uploads, previous
hashes, order, paging) is mapservice/core/change_feed.py, shared with the memory twin.
The uploads alone (the timeline's marks) are found from per-writer write counts
(mapservice/core/upload_scan.py; before the newest snapshot kept in `chunk_bursts`,
schema v18), so a week of a large fleet is not read write by write.
On the read client.

`ClickHouseChangeFeed` (the ChangeFeed role) holds the connection only (the previous
contents come from the nearest valid map snapshot plus the writes after it, as map_at),
never another role's queries.
"""

from __future__ import annotations

from collections.abc import Collection

from mapservice.adapters.clickhouse import burst_schema
from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.core import change_scan, upload_scan
from mapservice.core.change_feed import UPLOADER_ID, ChangeEntry, ChangeQuery
from mapservice.core.ports import ChunkRow


class ClickHouseChangeFeed:
    """Map changes and uploads of a window, page by page."""

    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def change_feed(self, query: ChangeQuery) -> list[ChangeEntry]:
        if query.kind == "upload":
            return upload_scan.newest_first(query, self._write_bursts, self._feed_writes)
        return change_scan.newest_first(query, self._feed_writes, self._hashes_before)

    def _write_bursts(self, from_ms: int, to_ms: int, robot: str | None) -> list[tuple[str, int]]:
        # Whole buckets before the newest valid snapshot from chunk_bursts (written by its
        # builds: a few rows a day), the rest (at most a snapshot interval) counted from
        # chunk_events. A whole bucket's count is at least its count within the span, and
        # chunk_events is counted without FINAL (a write stored twice until a merge): both
        # can only add a bucket, which the writes read for it (FINAL) then settle.
        db, b = self.connection.database, upload_scan.BURST_BUCKET_MS
        ((snap,),) = self.connection.rows(
            f"SELECT toUnixTimestamp64Milli(maxOrNull(snap_ts)) FROM {db}.snapshot_log "
            f"WHERE snap_ts < {self.connection.valid_before()}",
            {},
        )
        cut = from_ms if snap is None else max(from_ms, min(to_ms, snap // b * b))
        only = "" if robot is None else " AND robot_id = {r:String}"
        params = {
            "f": from_ms,
            "t": to_ms,
            "c": cut,
            "fb": from_ms // b * b // 1000,
            "cs": -(-cut // 1000),
            "r": robot or "",
            "b": b,
            "n": upload_scan.BURST_MIN_WRITES,
            "up": UPLOADER_ID,
        }
        rows = (
            self.connection.rows(
                "SELECT robot_id, toInt64(toUnixTimestamp(bucket)) * 1000 "
                f"FROM {db}.{burst_schema.TABLE} FINAL "
                "WHERE bucket >= toDateTime({fb:Int64}) AND bucket < toDateTime({cs:Int64})"
                f"{only} {FINAL_SETTINGS}",
                params,
            )
            if cut > from_ms
            else []
        )
        if cut < to_ms:
            rows += self.connection.rows(
                "SELECT robot_id, intDiv(toUnixTimestamp64Milli(ts), {b:Int64}) * {b:Int64} AS bucket "
                f"FROM {db}.chunk_events "
                "PREWHERE ts >= fromUnixTimestamp64Milli({c:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
                f"{only.replace(' AND', ' WHERE', 1)} GROUP BY robot_id, bucket "
                "HAVING count() >= {n:UInt32} OR robot_id = {up:String}",
                params,
            )
        return [(r[0], int(r[1])) for r in rows]

    def _feed_writes(
        self, from_ms: int, to_ms: int, robots: Collection[str] | None
    ) -> list[ChunkRow]:
        # A slice is a range of the sorting key's leading `ts`: its granules only.
        robot = "" if robots is None else " AND robot_id IN {rs:Array(String)}"
        rows = self.connection.rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)) "
            f"FROM {self.connection.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
            f"{robot} ORDER BY ts, row, col, robot_id {FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "rs": sorted(robots or ())},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2]) for r in rows]

    def _hashes_before(
        self, chunks: set[tuple[int, int]], before_ms: int
    ) -> dict[tuple[int, int], str]:
        """Per chunk, the content of its latest write (by event time, robot id) before
        `before_ms`: the nearest valid snapshot at or before it plus the writes since (at
        most a snapshot interval), not every write of the history before it. Without such a
        snapshot, the oldest valid one's rows older than `before_ms` and the kept writes: the
        retention drops the days before its anchor snapshot (at most the boundary; the
        window's margin may start before it), so a chunk last written then has its content
        in the snapshots only (the floor carried forward)."""
        if not chunks:
            return {}
        db = self.connection.database
        wanted = (
            "(row, col) IN (SELECT tupleElement(c, 1), tupleElement(c, 2) "
            "FROM (SELECT arrayJoin({cs:Array(Tuple(UInt16, UInt16))}) AS c))"
        )
        rows = self.connection.rows(
            f"WITH (SELECT maxOrNull(snap_ts) FROM {db}.snapshot_log "
            "WHERE snap_ts <= fromUnixTimestamp64Milli({b:Int64}) "
            f"AND snap_ts < {self.connection.valid_before()}) AS before_snap, "
            f"ifNull(before_snap, (SELECT minOrNull(snap_ts) FROM {db}.snapshot_log "
            f"WHERE snap_ts < {self.connection.valid_before()})) AS snap, "
            "ifNull(before_snap, toDateTime64(0, 3)) AS writes_after "
            "SELECT row, col, lower(hex(argMax(content_hash, (ts, robot_id)))) FROM ("
            f"SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots "
            f"WHERE snap_ts = snap AND ts < fromUnixTimestamp64Milli({{b:Int64}}) AND {wanted} "
            "UNION ALL "
            f"SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events "
            f"PREWHERE ts > writes_after AND ts < fromUnixTimestamp64Milli({{b:Int64}}) WHERE {wanted}) "
            "GROUP BY row, col",
            {"b": before_ms, "cs": sorted(chunks)},
        )
        return {(int(r[0]), int(r[1])): r[2] for r in rows}
