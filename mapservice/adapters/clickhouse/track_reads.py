"""The store's reads of one robot over a window (its track, and the plot panel's
per-bucket aggregates), from `pose_tracks` (schema v17: poses sorted by (robot_id, ts)), on
the read client.

`ClickHouseTrackReads` holds the connection only, never another role's queries; the
time-travel reader (reads.py) answers `robot_track` through it.
"""

from __future__ import annotations

import math

from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.adapters.clickhouse.track_schema import TABLE
from mapservice.core.ports import PoseRow, TrackBucket

# POSE_READ_COLUMNS without the planned path (has_path false, no path text): a plot never
# draws it, and its arrays are most of what a pose row weighs.
_TRACK_COLUMNS = (
    "robot_id, toUnixTimestamp64Milli(ts), x_mm / 1000, y_mm / 1000, z_mm / 1000, "
    "qx, qy, qz, qw, battery, charging, loaded, false, '', "
    "toUnixTimestamp64Milli(ts) + recv_lag_ms"
)


class ClickHouseTrackReads:
    """One robot's poses over a window."""

    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def robot_track(
        self, robot_id: str, from_ms: int, to_ms: int, step_ms: int = 0, limit: int = 100_000
    ) -> list[PoseRow]:
        # The primary key (robot_id, ts) finds the robot's granules of the window: one
        # contiguous range, whatever the size of the fleet. PREWHERE on key columns only, so
        # FINAL still sees every duplicate of an identity (as poses() does).
        if step_ms < 0:
            raise ValueError("step_ms must not be negative")
        every = (
            ""
            if step_ms == 0
            else "LIMIT 1 BY intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64}) "
        )
        return self.connection.pose_query(
            f"SELECT {_TRACK_COLUMNS} FROM {self.connection.database}.{TABLE} FINAL "
            "PREWHERE robot_id = {r:String} AND ts >= fromUnixTimestamp64Milli({f:Int64}) "
            "AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts {every}LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            {"r": robot_id, "f": from_ms, "t": to_ms, "s": max(step_ms, 1), "n": limit},
        )

    def track_buckets(
        self, robot_id: str, from_ms: int, to_ms: int, bucket_ms: int
    ) -> list[TrackBucket]:
        """core/track_buckets.py's rule in one query: FINAL keeps one pose per event time,
        the window function pairs each pose with the previous one of the window (its step,
        counted where it ends) and the buckets sum them. Positions are whole millimetres:
        a step's length is exact up to the square root."""
        if bucket_ms <= 0:
            raise ValueError("bucket_ms must be positive")
        rows = self.connection.rows(
            "SELECT intDiv(t, {b:Int64}) * {b:Int64} AS start, count(), countIf(n > 1), "
            "sumIf(sqrt(pow(x_mm - px, 2) + pow(y_mm - py, 2)), n > 1) / 1000, "
            "sumIf(t - pt, n > 1), min(t), max(t), min(battery), max(battery), avg(battery) "
            "FROM (SELECT toUnixTimestamp64Milli(ts) AS t, x_mm, y_mm, battery, "
            "row_number() OVER w AS n, lagInFrame(toUnixTimestamp64Milli(ts)) OVER w AS pt, "
            "lagInFrame(x_mm) OVER w AS px, lagInFrame(y_mm) OVER w AS py "
            f"FROM {self.connection.database}.{TABLE} FINAL "
            "PREWHERE robot_id = {r:String} AND ts >= fromUnixTimestamp64Milli({f:Int64}) "
            "AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "WINDOW w AS (ORDER BY ts ROWS BETWEEN 1 PRECEDING AND CURRENT ROW)) "
            f"GROUP BY start ORDER BY start {FINAL_SETTINGS}",
            {"r": robot_id, "f": from_ms, "t": to_ms, "b": bucket_ms},
        )
        return [
            TrackBucket(
                start_ms=int(start),
                poses=int(poses),
                steps=int(steps),
                distance_m=float(distance),
                step_ms=int(step_ms),
                first_ms=int(first),
                last_ms=int(last),
                battery_min=_level(lo),
                battery_max=_level(hi),
                battery_mean=None if mean is None or math.isnan(mean) else float(mean),
            )
            for start, poses, steps, distance, step_ms, first, last, lo, hi, mean in rows
        ]


def _level(value: float | None) -> float | None:
    return None if value is None else float(value)
