"""What each table and column of the history holds, in words: ClickHouse's table and column
comments, which analysts see in their SQL client, and docs/analysts.md's storage reference.

Data only (analyst_schema.py renders the statements and the guide's reference from it)."""

from __future__ import annotations

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
    "incidents": (
        "What went wrong on the floor, found by the processors from the poses: near misses, "
        "stuck and silent robots, low batteries; and from the records beside them: keep-out "
        "zone violations, map conflicts, VDA 5050 FATAL errors and disconnections, failed "
        "commands (schema v19). One row per finding: read with FINAL and leave out "
        "retracted rows.",
        {
            "incident_id": "The incident: a digest of its kind, robots and start",
            "kind": "near_miss, stuck, offline, battery_low, zone_violation, conflict, "
            "vda_error or command_failed",
            "robots": "The robots involved (two for a near miss; a conflict: the robot whose "
            "writes conflicted, then the others), sorted",
            "start": "When it began (UTC): the first close tick, when the robot stopped, its "
            "last report before the silence, its first low report, the first message or "
            "pose that made it",
            "end": "When it was last seen (UTC); now for a silence, disconnection or error "
            "still going on",
            "ongoing": "It still held at the newest pose or message known when it was found",
            "x": "Where, in metres (a near miss: halfway between the robots at their "
            "closest; one found from messages: where its robot last was)",
            "y": "Where, in metres",
            "severity": "warning or critical",
            "measure": "The closest distance in metres (near_miss), the seconds stopped "
            "(stuck), silent or disconnected (offline), inside (zone_violation), in error "
            "(vda_error) or waiting for the ack (command_failed), the lowest level in percent "
            "(battery_low), the conflicting chunk writes (conflict)",
            "evidence": "The poses (or the messages, by robot and instant, where the robot "
            "was) that made it, as JSON [[robot_id, ts_ms, x, y], ...]",
            "found": "When the processors found it (the latest finding replaces earlier ones)",
            "retracted": "A later history no longer holds it (a late pose broke it)",
        },
    ),
    "webhooks": (
        "State: the webhooks operators registered for the incident alerts (schema v20). "
        "Read with FINAL and leave out removed rows; no secret is stored (each is derived "
        "from the service's signing key).",
        {
            "webhook_id": "The webhook (wh- and 16 hex digits)",
            "url": "Where its deliveries are POSTed (http or https, no credentials)",
            "kinds": "The incident kinds it gets; empty: all",
            "created": "When it was registered (UTC)",
            "created_by": "The name of the credential that registered it, never the token",
            "resumed": "The latest resume an operator asked for (UTC; the epoch: none)",
            "removed": "It was removed at `changed`",
            "changed": "When this row was saved (the latest row is the webhook's)",
        },
    ),
    "webhook_reports": (
        "State: each processors replica's latest report of its deliveries to each webhook "
        "(schema v20), counts since that replica started. Read with FINAL; a replica gone "
        "leaves its last report behind.",
        {
            "webhook_id": "The webhook",
            "replica": "The processors replica (host:pid)",
            "reported": "When it reported (UTC)",
            "paused_reason": "Why its deliveries are paused (a delivery failed every try); "
            "empty: active",
            "last_error": "The last failed try's error",
            "last_try": "When its last try ended (UTC; the epoch: none yet)",
            "last_result": "That try's result: delivered, or its error",
            "delivered": "Deliveries the receiver answered 2xx",
            "failed_tries": "Tries that failed (no answer in time, refused, not 2xx)",
            "dropped": "Deliveries dropped unsent (the queues' bound)",
            "queued": "Deliveries waiting to be sent",
        },
    ),
    "heatmap_cells": (
        "Derived: per 10-minute bucket and 0.5 m cell the robots' samples (a robot's first "
        "pose of each second), still samples and known speeds there, for the heatmaps "
        "(mapservice/core/heatmaps.py has the rule), for the buckets before the newest "
        "snapshot, written by the snapshot builds (schema v21). Duplicates until merged: "
        "read with FINAL.",
        {
            "bucket": "The bucket's start (UTC)",
            "i": "The cell's column: x in [i * 0.5, (i + 1) * 0.5) metres",
            "j": "The cell's row: y in [j * 0.5, (j + 1) * 0.5) metres",
            "samples": "Robot-seconds: the robots' samples in the cell (occupancy)",
            "still": "Samples slower than the moving threshold (dwell seconds)",
            "speeds": "Samples whose speed is known (the previous within the offline threshold)",
            "speed_sum": "The sum of those speeds, m/s (mean speed = speed_sum / speeds)",
            "built": "When the row was written",
        },
    ),
}


# Schema v9 re-creates pose_keyframes (sorted by time): its comments again.
TABLE_COMMENTS_V9_KEYFRAMES = {"pose_keyframes": TABLE_COMMENTS["pose_keyframes"]}

# Schema v19 created incidents with the comments of the first four kinds; v22 replaces them
# with LATER_TABLE_COMMENTS' (a released migration's statements never change).
INCIDENTS_V19_COMMENTS: dict[str, tuple[str, dict[str, str]]] = {
    "incidents": (
        "What went wrong on the floor, found by the processors from the poses: near misses, "
        "stuck and silent robots, low batteries (schema v19). One row per finding: read with "
        "FINAL and leave out retracted rows.",
        {
            "incident_id": "The incident: a digest of its kind, robots and start",
            "kind": "near_miss, stuck, offline or battery_low",
            "robots": "The robots involved (two for a near miss), sorted",
            "start": "When it began (UTC): the first close tick, when the robot stopped, its "
            "last report before the silence, its first low report",
            "end": "When it was last seen (UTC); now for a silence still going on",
            "ongoing": "It still held at the newest pose known when it was found",
            "x": "Where, in metres (a near miss: halfway between the robots at their closest)",
            "y": "Where, in metres",
            "severity": "warning or critical",
            "measure": "The closest distance in metres (near_miss), the seconds stopped "
            "(stuck) or silent (offline), the lowest level in percent (battery_low)",
            "evidence": "The poses that made it, as JSON [[robot_id, ts_ms, x, y], ...]",
            "found": "When the processors found it (the latest finding replaces earlier ones)",
            "retracted": "A later history no longer holds it (a late pose broke it)",
        },
    )
}
