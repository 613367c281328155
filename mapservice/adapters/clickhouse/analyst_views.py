"""The analysts' views (migration 7's, and later ones'): clean types and units (metres,
degrees, booleans, UTC times), so nobody needs the storage codecs; each with its comment and
its columns' meanings.

Data only (analyst_schema.py renders the statements and the guide's reference from it)."""

from __future__ import annotations

from mapservice.adapters.clickhouse import vda_views

# Shared by the views: the latest map geometry, for chunk coordinates of a position.
_META = """(SELECT meta FROM {db}.map_meta FINAL ORDER BY ts DESC LIMIT 1) AS _meta,
    JSONExtractFloat(_meta, 'resolution') AS _res,
    JSONExtractFloat(_meta, 'origin', 1) AS _ox,
    JSONExtractFloat(_meta, 'origin', 2) AS _oy,
    JSONExtractUInt(_meta, 'height') AS _map_h,
    JSONExtractUInt(_meta, 'CHUNK_WIDTH') AS _cw,
    JSONExtractUInt(_meta, 'CHUNK_HEIGHT') AS _ch"""


def _flag(column: str) -> str:
    """A 2019 flag sent as a JSON boolean, as Nullable(Bool); anything else is NULL."""
    return f"CAST(multiIf({column} = 'true', 1, {column} = 'false', 0, NULL) AS Nullable(Bool))"


VIEWS: dict[str, tuple[str, str, dict[str, str]]] = {
    "robot_poses": (
        "Robot poses in metres, degrees and UTC, one row per report.",
        f"""
        WITH {_META}
        SELECT robot_id, ts AS at,
            x_mm / 1000 AS x_m, y_mm / 1000 AS y_m, z_mm / 1000 AS z_m,
            round(degrees(atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))), 3) AS heading_deg,
            battery AS battery_level,
            {_flag("charging")} AS charging, {_flag("loaded")} AS loaded,
            charging AS charging_raw, loaded AS loaded_raw,
            has_path, length(path_x_mm) AS path_points,
            ts + toIntervalMillisecond(recv_lag_ms) AS received_at,
            recv_lag_ms / 1000 AS receive_lag_s,
            if(_res > 0, toInt32(floor((_map_h - (y_m - _oy) / _res) / _ch)), NULL) AS chunk_row,
            if(_res > 0, toInt32(floor((x_m - _ox) / _res / _cw)), NULL) AS chunk_col
        FROM {{db}}.poses FINAL""",
        {
            "robot_id": "The robot",
            "at": "Event time (UTC, ms)",
            "x_m": "x in metres (map frame)",
            "y_m": "y in metres",
            "z_m": "z in metres",
            "heading_deg": "Yaw from the quaternion, degrees, -180..180, 0 = +x, 90 = +y",
            "battery_level": "Battery level as sent (the simulator: percent); NULL if absent",
            "charging": "true/false if the robot sent a JSON boolean, else NULL",
            "loaded": "true/false if the robot sent a JSON boolean, else NULL",
            "charging_raw": "charging as sent (JSON text; '' if absent)",
            "loaded_raw": "loaded as sent (JSON text; '' if absent)",
            "has_path": "Whether a planned path was sent",
            "path_points": "Its number of points",
            "received_at": "When the gateway received the report (UTC, ms)",
            "receive_lag_s": "received_at - at in seconds (clock skew plus transport delay)",
            "chunk_row": "Map chunk row the position lies in (latest map geometry; NULL without "
            "resolution)",
            "chunk_col": "Map chunk column the position lies in",
        },
    ),
    "chunk_changes": (
        "Map chunk writes, one row per write.",
        """
        SELECT ts AS at, row AS chunk_row, col AS chunk_col, robot_id,
            lower(hex(content_hash)) AS content_hash,
            ts + toIntervalMillisecond(recv_lag_ms) AS received_at,
            recv_lag_ms / 1000 AS receive_lag_s
        FROM {db}.chunk_events FINAL""",
        {
            "at": "Event time of the write (UTC, ms)",
            "chunk_row": "Chunk row (0 = top)",
            "chunk_col": "Chunk column (0 = left)",
            "robot_id": "The writing robot",
            "content_hash": "BLAKE2b-128 of the raw pixels, hex",
            "received_at": "When the gateway received it",
            "receive_lag_s": "received_at - at, s",
        },
    ),
    "chunk_conflicts": (
        "Conflicting writes: a later write and the latest different write "
        "of another robot to the same chunk within the window.",
        """
        SELECT ts AS at, row AS chunk_row, col AS chunk_col, robot_b AS robot_id,
            robot_a AS other_robot_id, ts_a AS other_at,
            dateDiff('millisecond', ts_a, ts) / 1000 AS seconds_apart
        FROM {db}.conflicts FINAL""",
        {
            "at": "Time of the later write",
            "chunk_row": "Chunk row",
            "chunk_col": "Chunk column",
            "robot_id": "Robot of the later write",
            "other_robot_id": "Robot of the earlier write",
            "other_at": "Time of the earlier write",
            "seconds_apart": "at - other_at in seconds",
        },
    ),
    "dead_letter_messages": (
        "Refused messages with their reason.",
        """
        SELECT received AS received_at, reason, mqtt_topic, detail, gateway,
            length(payload) AS payload_bytes
        FROM {db}.dead_letters""",
        {
            "received_at": "When received (UTC, ms)",
            "reason": "Why refused",
            "mqtt_topic": "The MQTT topic",
            "detail": "The validation error",
            "gateway": "The refusing gateway instance",
            "payload_bytes": "Bytes of payload stored (at most 64 KB)",
        },
    ),
    "robot_minutes": (
        "Per robot and minute with reports: activity and battery.",
        """
        SELECT robot_id, toStartOfMinute(at) AS minute, count() AS poses,
            round(sum(step_m), 3) AS distance_m,
            avg(battery_level) AS battery_level_avg, min(battery_level) AS battery_level_min,
            max(charging) AS charging, max(loaded) AS loaded
        FROM (
            SELECT robot_id, at, battery_level, charging, loaded,
                sqrt(pow(x_m - lagInFrame(x_m, 1, x_m) OVER w, 2)
                     + pow(y_m - lagInFrame(y_m, 1, y_m) OVER w, 2)) AS step_m
            FROM {db}.robot_poses
            WINDOW w AS (PARTITION BY robot_id ORDER BY at ROWS BETWEEN 1 PRECEDING AND CURRENT ROW))
        GROUP BY robot_id, minute""",
        {
            "robot_id": "The robot",
            "minute": "Start of the minute (UTC)",
            "poses": "Reports in the minute",
            "distance_m": "Distance moved in the minute, metres (straight lines between reports; "
            "the step into the minute counts in it)",
            "battery_level_avg": "Mean battery level",
            "battery_level_min": "Lowest battery level",
            "charging": "Charging at any report in the minute (NULL: never sent as boolean)",
            "loaded": "Loaded at any report in the minute",
        },
    ),
}


# Views of later schemas (each migration creates its own: migration 7's text, and so its
# checksum, stays as it was applied).
LATER_VIEWS: dict[str, tuple[str, str, dict[str, str]]] = {
    "keep_out_violations": (
        "A robot's stored pose inside a keep-out zone, with the zone as it "
        "stood then (its name, who last drew it and when; schema v15).",
        """
        SELECT v.ts AS at, v.robot_id AS robot_id, v.annotation_id AS zone_id,
            e.name AS zone_name, e.ts AS zone_drawn_at, e.author AS zone_drawn_by,
            v.x AS x_m, v.y AS y_m
        FROM (SELECT ts, robot_id, annotation_id, x, y FROM {db}.zone_violations FINAL) AS v
        ASOF LEFT JOIN (
            SELECT annotation_id, ts, name, author FROM {db}.annotation_events FINAL
            WHERE change != 'removed') AS e
        ON v.annotation_id = e.annotation_id AND v.ts >= e.ts""",
        {
            "at": "The pose's event time (UTC, ms)",
            "robot_id": "The robot",
            "zone_id": "The keep-out zone's id (annotation_events.annotation_id)",
            "zone_name": "The zone's name at that time",
            "zone_drawn_at": "When the zone got the shape it had then (its create or last change)",
            "zone_drawn_by": "Who made that edit (an operator credential's name)",
            "x_m": "The pose's x in metres (map frame)",
            "y_m": "The pose's y in metres",
        },
    ),
}


# The VDA 5050 vehicles' views (schema v16) live in their own module.
LATER_VIEWS.update(vda_views.VIEWS)
