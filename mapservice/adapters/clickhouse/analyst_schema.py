"""What analysts see in the schema: table and column comments, and views with clean types
and units (metres, degrees, booleans, UTC times), so nobody needs the storage codecs.

Migration 7 applies it (mapservice/adapters/clickhouse/schema.py); docs/analysts.md documents every table,
view and column named here, and a test holds the two together."""

from __future__ import annotations

from mapservice.adapters.clickhouse import vda_views

TABLE_COMMENTS: dict[str, tuple[str, dict[str, str]]] = {
    "poses": (
        "One row per robot pose report (MQTT iot/coordinates/<robot>). Identity "
        "(robot_id, ts); read with FINAL. Analysts: use the view robot_poses.",
        {
            "robot_id": "The robot's id as it reported it",
            "ts": "Event time: the robot's own timestamp (UTC, ms)",
            "x_mm": "Position x in millimetres in the map frame",
            "y_mm": "Position y in millimetres in the map frame",
            "z_mm": "Position z in millimetres",
            "qx": "Orientation quaternion x",
            "qy": "Orientation quaternion y",
            "qz": "Orientation quaternion z",
            "qw": "Orientation quaternion w",
            "battery": "status.battery.battery_level as sent (the simulator: percent)",
            "charging": "status.battery.charging as JSON text as sent ('' if absent)",
            "loaded": "status.loaded as JSON text as sent ('' if absent)",
            "has_path": "Whether the report carried a planned path",
            "path_x_mm": "Planned path x coordinates in millimetres",
            "path_y_mm": "Planned path y coordinates in millimetres",
            "recv_lag_ms": "Receive time minus event time in ms (clock skew plus transport delay)",
        },
    ),
    "chunk_events": (
        "One row per chunk write (MQTT iot/chunks/create or REST POST /chunks). "
        "Identity (ts, row, col, robot_id); read with FINAL. Analysts: use "
        "the view chunk_changes.",
        {
            "ts": "Event time: the robot's timestamp of the write (UTC, ms)",
            "row": "Chunk row in the map grid (0 is the top)",
            "col": "Chunk column in the map grid (0 is the left)",
            "robot_id": "The writing robot",
            "content_hash": "BLAKE2b-128 of the chunk's raw pixels (16 bytes); joins chunk_contents",
            "recv_lag_ms": "Receive time minus event time in ms",
        },
    ),
    "chunk_contents": (
        "Chunk pixels, once per content hash and day.",
        {
            "content_hash": "BLAKE2b-128 of the raw pixels (16 bytes)",
            "day": "UTC day the content was (first) written that day",
            "width": "Chunk width in pixels",
            "height": "Chunk height in pixels",
            "zlib_pixels": "The pixels, zlib-compressed (8-bit grey, row-major, 0 = occupied)",
        },
    ),
    "map_meta": (
        "Every map geometry ever set (the 2019 meta.json); the latest one holds.",
        {
            "ts": "When it was set (UTC, ms)",
            "robot_id": "Who set it",
            "meta": "The 2019 meta.json document plus ROS resolution and origin",
        },
    ),
    "dead_letters": (
        "Messages the gateway refused, with the reason. Analysts: use the view "
        "dead_letter_messages.",
        {
            "received": "When the gateway received it (UTC, ms)",
            "reason": "Why it was refused (e.g. not_json, bad_timestamp, too_deep)",
            "mqtt_topic": "The MQTT topic it came on",
            "detail": "The validation error's text",
            "payload": "The payload (the first 64 KB of larger ones)",
            "gateway": "The gateway instance that refused it",
        },
    ),
    "map_snapshots": (
        "Derived: the map at each snapshot instant (which write holds each "
        "chunk). The service's time-travel reads use it.",
        {
            "snap_ts": "Snapshot instant",
            "row": "Chunk row",
            "col": "Chunk column",
            "ts": "Time of the write that holds the chunk",
            "robot_id": "Its robot",
            "content_hash": "Its content",
            "built": "When the snapshot was built",
        },
    ),
    "robot_snapshots": (
        "Derived: each robot's latest pose time at each snapshot instant.",
        {
            "snap_ts": "Snapshot instant",
            "robot_id": "The robot",
            "ts": "Time of its latest pose at or before snap_ts",
            "built": "When built",
        },
    ),
    "snapshot_log": (
        "Derived: which snapshots exist.",
        {
            "snap_ts": "Snapshot instant",
            "built": "When built",
            "chunks": "Chunks in it",
            "robots": "Robots in it",
        },
    ),
    "conflicts": (
        "Two robots writing different content to one chunk within the conflict "
        "window: one row per later write. Analysts: use the view chunk_conflicts.",
        {
            "ts": "Time of the later write (B)",
            "row": "Chunk row",
            "col": "Chunk column",
            "robot_b": "The robot of the later write",
            "robot_a": "The robot of the earlier write",
            "ts_a": "Time of the earlier write (A)",
        },
    ),
    "pose_keyframes": (
        "Derived: each robot's first pose of every minute (downsampled reads).",
        {
            "cell": "The minute",
            "rank": "Internal: keeps the minute's earliest pose",
        },
    ),
    "schema_migrations": (
        "Applied schema migrations.",
        {
            "version": "Migration number",
            "description": "What it did",
            "applied": "When",
            "checksum": "SHA-256 of its statements (an edited migration is refused)",
        },
    ),
}

# Tables added after migration 7 (their comments come with their own migration).
LATER_TABLE_COMMENTS: dict[str, tuple[str, dict[str, str]]] = {
    "snapshot_repairs": (
        "Derived: snapshots a late event made wrong, from `from_ts` on; reads "
        "skip them until the snapshot timer has rebuilt them (schema v8).",
        {
            "from_ts": "Snapshots at or after this instant are being rebuilt",
            "noted": "When the late event (or a repair step) noted it",
        },
    ),
    "pose_minutes": (
        "Derived: each robot's first and last pose time of every minute, written "
        "by a materialized view on poses (schema v9); the timeline's robots "
        "per bucket. Rows of one minute may be unmerged: take min/max.",
        {
            "cell": "The minute (UTC)",
            "robot_id": "The robot",
            "first_ts": "Its first pose time in the minute (min over the rows)",
            "last_ts": "Its last pose time in the minute (max over the rows)",
        },
    ),
    "pose_ten_minutes": (
        "Derived: as pose_minutes, per ten minutes (schema v9).",
        {
            "cell": "The start of the ten minutes (UTC)",
            "robot_id": "The robot",
            "first_ts": "Its first pose time in them (min over the rows)",
            "last_ts": "Its last pose time in them (max over the rows)",
        },
    ),
    "pose_derivations": (
        "Not storage: a Null table (it keeps nothing). The history consumer "
        "writes each batch's poses into it after the batch is stored in poses "
        "and pushed live; the materialized views on it fill pose_keyframes, "
        "pose_minutes and pose_ten_minutes (schema v10). Its columns are "
        "those of poses. Always empty when read.",
        {},
    ),
    "carried_poses": (
        "Each robot's last pose older than the days kept (a robot silent "
        "since then), one row per robot, carried by the retention step so the "
        "robots at any instant of the retention stay whole (schema v11). Its "
        "columns are those of poses. Read with FINAL.",
        {},
    ),
    "chunk_seconds": (
        "Derived: the chunk writes of every second before the newest snapshot, "
        "deduplicated, written with the snapshots (schema v9); the timeline's "
        "chunk changes per bucket. Read with FINAL.",
        {
            "second": "The second (UTC)",
            "offsets": "Millisecond offsets in the second of its writes, sorted, one per write",
            "changes": "The number of its writes (length of offsets)",
            "built": "When written (a repaired snapshot rewrites its seconds)",
        },
    ),
    # Schema v12: VDA 5050 vehicles (robot id `<manufacturer>:<serialNumber>`, escaped).
    "vda_states": (
        "VDA 5050 vehicle states (and visualizations off the known maps): status "
        "and position as reported, in the vehicle's map frame (schema v12)",
        {
            "robot_id": "The vehicle's robot id: manufacturer and serial number, escaped",
            "ts": "The state's timestamp (UTC)",
            "manufacturer": "As the vehicle sent it",
            "serial_number": "As the vehicle sent it",
            "vda_version": "The VDA 5050 schema it was validated against",
            "map_id": "The vehicle's mapId; NULL when it reported no position",
            "on_known_map": "true: mapId has a transform and the pose is in `poses`; false: "
            "flagged, not drawn",
            "x": "Metres in the vehicle's mapId frame, as reported",
            "y": "Metres in the vehicle's mapId frame, as reported",
            "theta": "Radians in the vehicle's mapId frame, as reported",
            "driving": "Whether it was driving",
            "paused": "Whether it was paused",
            "operating_mode": "AUTOMATIC, SEMIAUTOMATIC, MANUAL, SERVICE or TEACHIN",
            "order_id": "The order it was executing (empty: none)",
            "error_count": "Its active errors and warnings (rows of vda_errors)",
        },
    ),
    "vda_errors": (
        "VDA 5050 errors and warnings: one row per error active in a state (schema v12)",
        {
            "robot_id": "The vehicle's robot id",
            "ts": "The state's timestamp (UTC)",
            "level": "WARNING or FATAL (3.0: also URGENT, CRITICAL)",
            "type": "The vehicle's errorType",
            "description": "The vehicle's errorDescription",
        },
    ),
    "vda_connections": (
        "VDA 5050 connection states: exact online/offline instants (schema v12)",
        {
            "robot_id": "The vehicle's robot id",
            "ts": "When the state holds: the message time, or for CONNECTIONBROKEN (the last "
            "will, composed at connect time) when the gateway received it",
            "state": "ONLINE, OFFLINE or CONNECTIONBROKEN",
            "sent_ts": "The message's own timestamp",
        },
    ),
    "chunk_bursts": (
        "Derived: per writer and 20 s bucket its number of chunk writes, kept "
        "where a map upload may be (10 or more; every bucket of map-upload), for "
        "the buckets before the newest snapshot, written by the snapshot builds "
        "(schema v18). Duplicates until merged: read with FINAL.",
        {
            "bucket": "The bucket's start (UTC)",
            "robot_id": "The writer",
            "writes": "Its chunk writes in the bucket",
            "built": "When the row was written",
        },
    ),
    "pose_tracks": (
        "Derived: every pose of poses again, sorted by (robot_id, ts), for "
        "reads of one robot over a window (its plots and track), written by a "
        "materialized view on pose_derivations (schema v17). Columns as poses; "
        "duplicates until merged: read with FINAL.",
        {
            "robot_id": "The robot",
            "ts": "The pose's event time (UTC)",
        },
    ),
    "vda_factsheets": (
        "VDA 5050 factsheets, as the vehicle sent them (schema v12)",
        {
            "robot_id": "The vehicle's robot id",
            "ts": "The factsheet's timestamp (UTC)",
            "vda_version": "The VDA 5050 schema it was validated against",
            "factsheet": "The factsheet's JSON",
        },
    ),
    "annotation_events": (
        "Operators' annotations (points of interest, zones): every create, "
        "change and removal with who and when (schema v13); the annotations "
        "at T are each id's latest event at or before T, unless a removal",
        {
            "annotation_id": "The annotation's id",
            "ts": "When the edit was made (UTC)",
            "event_id": "The edit's event id",
            "change": "created, changed or removed",
            "author": "The credential that made the edit (a name, never the token)",
            "shape": "poi or zone ('' for a removal)",
            "kind": "station, charger, door, note (poi); keep_out, speed_limit, note (zone)",
            "name": "The annotation's name",
            "body": "The annotation as JSON, as the API returns it ('' for a removal)",
        },
    ),
    "command_events": (
        "Operators' commands to robots and the robots' answers (schema v14): "
        "event 'issued' (who sent what to which robot), 'ack' and 'outcome' "
        "(the robot's, at its own time); a command's answers share its "
        "command_id and robot_id",
        {
            "ts": "When the command was issued, or the robot's time of its answer (UTC)",
            "robot_id": "The robot the command was sent to (and that answered)",
            "command_id": "The command's id",
            "event": "issued, ack or outcome",
            "event_id": "The event's id",
            "kind": "pause, resume, goto_poi or cancel ('' for an answer)",
            "status": "accepted or rejected (ack); done, failed or cancelled (outcome); '' (issued)",
            "by": "The credential that issued the command (a name, never the token); the robot "
            "for an answer",
            "poi_id": "A goto_poi's point of interest (annotation_events.annotation_id)",
            "x": "A goto_poi's target x in metres",
            "y": "A goto_poi's target y in metres",
            "heading": "A goto_poi's target heading in radians, if the point has one",
            "reason": "Why a robot rejected a command or failed it",
        },
    ),
    "zone_violations": (
        "A robot's stored pose inside a keep-out zone, found by the processors (schema v13)",
        {
            "ts": "The pose's event time (UTC)",
            "robot_id": "The robot",
            "annotation_id": "The keep-out zone (annotation_events.annotation_id)",
            "x": "The pose's x in metres",
            "y": "The pose's y in metres",
        },
    ),
}


def comments_of(*tables: str) -> dict[str, tuple[str, dict[str, str]]]:
    """The comments of some later tables (each migration applies those of its own)."""
    return {t: LATER_TABLE_COMMENTS[t] for t in tables}


# Schema v9 re-creates pose_keyframes (sorted by time): its comments again.
TABLE_COMMENTS_V9_KEYFRAMES = {"pose_keyframes": TABLE_COMMENTS["pose_keyframes"]}

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


def later_view_statements(db: str, *views: str) -> list[str]:
    return [
        f"CREATE OR REPLACE VIEW {db}.{view} AS {LATER_VIEWS[view][1].format(db=db)} "
        f"COMMENT {_quote(LATER_VIEWS[view][0])}"
        for view in views
    ]


def _quote(text: str) -> str:
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def comment_statements(db: str, tables: dict[str, tuple[str, dict[str, str]]]) -> list[str]:
    out: list[str] = []
    for table, (comment, columns) in tables.items():
        out.append(f"ALTER TABLE {db}.{table} MODIFY COMMENT {_quote(comment)}")
        if not columns:  # a table whose columns are another's (described there)
            continue
        out.append(
            f"ALTER TABLE {db}.{table} "
            + ", ".join(
                f"COMMENT COLUMN {column} {_quote(text)}" for column, text in columns.items()
            )
        )
    return out


def statements(db: str) -> tuple[str, ...]:
    """Migration 7: the comments of the tables it knew, and the views."""
    return (*comment_statements(db, TABLE_COMMENTS), *view_statements(db, VIEWS))


def view_statements(db: str, views: dict[str, tuple[str, str, dict[str, str]]]) -> tuple[str, ...]:
    """The views (re)created, each with its comment (migration 7's; later ones add theirs)."""
    return tuple(
        f"CREATE OR REPLACE VIEW {db}.{view} AS {select.format(db=db)} COMMENT {_quote(comment)}"
        for view, (comment, select, _columns) in views.items()
    )


# The VDA 5050 vehicles' views (schema v16) live in their own module.
LATER_VIEWS.update(vda_views.VIEWS)


def reference_markdown() -> str:
    """The reference part of docs/analysts.md (a test keeps the guide equal to it; after a
    schema change: `python -m mapservice.adapters.clickhouse.analyst_schema` prints it)."""
    out = ["### Views (start here)", ""]
    for view, (comment, _select, columns) in {**VIEWS, **LATER_VIEWS}.items():
        out += [f"#### `{view}`", "", comment, "", "| column | meaning |", "| --- | --- |"]
        out += [f"| `{c}` | {text} |" for c, text in columns.items()]
        out.append("")
    out += ["### Tables (storage)", ""]
    for table, (comment, columns) in {**TABLE_COMMENTS, **LATER_TABLE_COMMENTS}.items():
        out += [f"#### `{table}`", "", comment, "", "| column | meaning |", "| --- | --- |"]
        out += [f"| `{c}` | {text} |" for c, text in columns.items()]
        out.append("")
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    print(reference_markdown(), end="")
