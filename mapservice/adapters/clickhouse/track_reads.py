"""The store's reads of one robot over a window (the plot panel's track), from
`pose_tracks` (schema v17: poses sorted by (robot_id, ts)), on the read client.

`ClickHouseTrackReads` holds the connection only, never another role's queries; the
time-travel reader (reads.py) answers `robot_track` through it.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.adapters.clickhouse.track_schema import TABLE
from mapservice.core.ports import PoseRow

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
