"""The heatmaps' read (the HeatmapReader role): a span's cells at a size, from
`heatmap_cells` (schema v21) for its whole buckets before the newest valid snapshot, and
from the poses by the same rule (heatmap_schema.samples_select) for the partial buckets at
its ends and the time after that snapshot; on the read client.

`ClickHouseHeatmapReads` holds the connection only, never another role's queries.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import heatmap_schema
from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.core.heatmaps import HeatmapCell, HeatmapRule


class ClickHouseHeatmapReads:
    """A span's heatmap cells."""

    def __init__(self, connection: ClickHouseConnection, rule: HeatmapRule | None = None) -> None:
        self.connection = connection
        self.heatmap_rule = rule or HeatmapRule()

    def heatmap_cells(
        self, from_ms: int, to_ms: int, factor: int, limit: int = 1_000_000
    ) -> list[HeatmapCell]:
        if factor < 1:
            raise ValueError("factor must be positive")
        db, b = self.connection.database, heatmap_schema.BUCKET_MS
        ((snap,),) = self.connection.rows(
            f"SELECT toUnixTimestamp64Milli(maxOrNull(snap_ts)) FROM {db}.snapshot_log "
            f"WHERE snap_ts < {self.connection.valid_before()}",
            {},
        )
        # Whole buckets [kept_from, kept_to) from the table, the rest from the poses.
        kept_from = -(-from_ms // b) * b
        kept_to = max(kept_from, min(to_ms // b * b, -1 if snap is None else snap // b * b))
        parts: list[str] = []
        if kept_to > kept_from:
            parts.append(
                f"SELECT i, j, samples, still AS still_n, speeds, speed_sum "
                f"FROM {db}.{heatmap_schema.TABLE} FINAL "
                "WHERE bucket >= toDateTime(intDiv({kf:Int64}, 1000)) "
                "AND bucket < toDateTime(intDiv({kt:Int64}, 1000))"
            )
            ends = [(from_ms, kept_from, "f", "kf"), (kept_to, to_ms, "kt", "t")]
        else:
            ends = [(from_ms, to_ms, "f", "t")]
        for lo, hi in ((f"{{{a}:Int64}}", f"{{{z}:Int64}}") for s, e, a, z in ends if s < e):
            samples = heatmap_schema.samples_select(db, lo, hi, self.heatmap_rule)
            parts.append(
                f"SELECT {heatmap_schema.CELL_I} AS i, {heatmap_schema.CELL_J} AS j, "
                f"{heatmap_schema.SUMS} FROM ({samples}) GROUP BY i, j"
            )
        rows = self.connection.rows(
            "SELECT toInt32(floor(i / {k:Int32})) AS ci, toInt32(floor(j / {k:Int32})) AS cj, "
            "sum(samples), sum(still_n), sum(speeds), sum(speed_sum) "
            f"FROM ({' UNION ALL '.join(parts)}) GROUP BY ci, cj ORDER BY ci, cj "
            f"LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "kf": kept_from, "kt": kept_to, "k": factor, "n": limit},
        )
        return [
            HeatmapCell(int(i), int(j), int(n), int(still), int(speeds), float(total))
            for i, j, n, still, speeds, total in rows
        ]
