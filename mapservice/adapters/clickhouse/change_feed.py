"""The store's change feed: the window's chunk writes (with the margin the upload rule
needs) and, for chunks first written inside the window, the content they had before; the
rule itself (uploads, previous hashes, order, paging) is mapservice/core/change_feed.py,
shared with the memory twin. On the read client.

`ChangeFeedMixin` builds on `connection` only, never on another mixin's queries.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse.connection import _FINAL_SETTINGS, ClickHouseConnection
from mapservice.core import change_feed
from mapservice.core.change_feed import ChangeEntry, ChangeQuery
from mapservice.core.ports import ChunkRow


class ChangeFeedMixin(ClickHouseConnection):
    """Map changes and uploads of a window, page by page."""

    def change_feed(self, query: ChangeQuery) -> list[ChangeEntry]:
        lo, hi = change_feed.fetch_window(query)
        rows = self._rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)) "
            f"FROM {self.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            {"f": lo, "t": hi, "n": change_feed.MAX_WRITES + 1},
        )
        writes = [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2]) for r in rows]
        return change_feed.page(writes, query, self._hashes_before(
            change_feed.chunks_needing_earlier(writes, query), lo))

    def _hashes_before(self, chunks: set[tuple[int, int]], before_ms: int) -> dict[tuple[int, int], str]:
        """Per chunk, the content of its latest write (by event time, robot id) before
        `before_ms`: the kept writes, and the snapshot rows older than it of the nearest
        valid snapshot at or before it, or else of the oldest one. The retention drops the
        days before its anchor snapshot (at most the boundary, the window's margin may
        start before it): a chunk last written then has its content in the snapshots only
        (the floor carried forward)."""
        if not chunks:
            return {}
        db = self.database
        wanted = ("(row, col) IN (SELECT tupleElement(c, 1), tupleElement(c, 2) "
                  "FROM (SELECT arrayJoin({cs:Array(Tuple(UInt16, UInt16))}) AS c))")
        rows = self._rows(
            f"WITH ifNull((SELECT maxOrNull(snap_ts) FROM {db}.snapshot_log "
            "WHERE snap_ts <= fromUnixTimestamp64Milli({b:Int64}) "
            f"AND snap_ts < {self._valid_before()}), (SELECT minOrNull(snap_ts) "
            f"FROM {db}.snapshot_log WHERE snap_ts < {self._valid_before()})) AS snap "
            "SELECT row, col, lower(hex(argMax(content_hash, (ts, robot_id)))) "
            f"FROM (SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots "
            f"WHERE snap_ts = snap AND ts < fromUnixTimestamp64Milli({{b:Int64}}) AND {wanted} "
            f"UNION ALL SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events FINAL "
            f"WHERE ts < fromUnixTimestamp64Milli({{b:Int64}}) AND {wanted}) "
            f"GROUP BY row, col {_FINAL_SETTINGS}",
            {"b": before_ms, "cs": sorted(chunks)},
        )
        return {(int(r[0]), int(r[1])): r[2] for r in rows}
