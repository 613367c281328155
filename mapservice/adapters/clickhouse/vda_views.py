"""Schema v16: the analysts' views of VDA 5050 vehicles (their tables are schema v12's,
vda_schema.py): states in degrees and booleans, errors and warnings, connection states as
online/offline spans, and the factsheets' main facts as columns.

Data only (analyst_schema.py renders the statements and the guide's reference from it)."""

from __future__ import annotations

# The robot id is `<manufacturer>:<serialNumber>`, each escaped (core/vda_ids.py); the
# views take both names from the state or the factsheet the vehicle sent.
VIEWS: dict[str, tuple[str, str, dict[str, str]]] = {
    "vehicle_states": (
        "VDA 5050 vehicle states, one row per state: position as reported in "
        "the vehicle's map frame, status as booleans, heading in degrees.",
        """
        SELECT robot_id, manufacturer, serial_number, ts AS at, vda_version, map_id,
            on_known_map, x AS x_m, y AS y_m, round(degrees(theta), 3) AS heading_deg,
            driving, paused, operating_mode, order_id, error_count
        FROM {db}.vda_states FINAL""",
        {
            "robot_id": "The vehicle's robot id (`<manufacturer>:<serialNumber>`, escaped)",
            "manufacturer": "As the vehicle sent it",
            "serial_number": "As the vehicle sent it",
            "at": "The state's timestamp (UTC, ms)",
            "vda_version": "The VDA 5050 version it was validated against",
            "map_id": "The vehicle's mapId (NULL: it reported no position)",
            "on_known_map": "true: the service has a transform for map_id and the pose is in "
            "robot_poses (in the map's frame); false: stored, not drawn",
            "x_m": "x in metres in the map_id frame, as reported",
            "y_m": "y in metres in the map_id frame, as reported",
            "heading_deg": "theta in degrees in the map_id frame, -180..180",
            "driving": "Whether it was driving",
            "paused": "Whether it was paused",
            "operating_mode": "AUTOMATIC, SEMIAUTOMATIC, MANUAL, SERVICE or TEACHIN",
            "order_id": "The order it was executing ('' none)",
            "error_count": "Its active errors and warnings (rows of vehicle_errors at `at`)",
        },
    ),
    "vehicle_errors": (
        "VDA 5050 errors and warnings: one row per error active in a state "
        "(an error active for a minute of 1 Hz states has 60 rows; it ends "
        "at the next state without it).",
        """
        SELECT robot_id, ts AS at, level, type AS error_type, description,
            level = 'WARNING' AS is_warning
        FROM {db}.vda_errors FINAL""",
        {
            "robot_id": "The vehicle's robot id",
            "at": "The state's timestamp (UTC, ms)",
            "level": "WARNING or FATAL (VDA 5050 3.0: also URGENT, CRITICAL)",
            "error_type": "The vehicle's errorType",
            "description": "Its errorDescription",
            "is_warning": "level is WARNING",
        },
    ),
    "vehicle_connections": (
        "VDA 5050 connection states as spans: each state from when it "
        "held until the vehicle's next one (NULL: still holds).",
        """
        SELECT robot_id, at, state, state = 'ONLINE' AS online, sent_at,
            nullIf(next_at, toDateTime64(0, 3, 'UTC')) AS until,
            if(isNull(until), NULL, dateDiff('millisecond', at, until) / 1000) AS duration_s
        FROM (SELECT robot_id, ts AS at, state, sent_ts AS sent_at,
                leadInFrame(ts, 1, toDateTime64(0, 3, 'UTC')) OVER (PARTITION BY robot_id
                    ORDER BY ts ROWS BETWEEN CURRENT ROW AND 1 FOLLOWING) AS next_at
              FROM {db}.vda_connections FINAL)""",
        {
            "robot_id": "The vehicle's robot id",
            "at": "When the state began: the message's timestamp; for CONNECTIONBROKEN (the "
            "broker's last will, composed at connect time) when the gateway received it",
            "state": "ONLINE, OFFLINE or CONNECTIONBROKEN",
            "online": "state is ONLINE",
            "sent_at": "The message's own timestamp",
            "until": "When the vehicle's next connection state began (NULL: none yet)",
            "duration_s": "until - at in seconds (NULL: still holds)",
        },
    ),
    "vehicle_factsheets": (
        "VDA 5050 factsheets, one row per factsheet sent: the main facts "
        "as columns, the whole as JSON.",
        """
        SELECT robot_id, ts AS at, vda_version,
            JSONExtractString(factsheet, 'manufacturer') AS manufacturer,
            JSONExtractString(factsheet, 'serialNumber') AS serial_number,
            JSONExtractString(factsheet, 'typeSpecification', 'seriesName') AS series_name,
            JSONExtractString(factsheet, 'typeSpecification', 'agvKinematic') AS kinematic,
            JSONExtractString(factsheet, 'typeSpecification', 'agvClass') AS vehicle_class,
            JSONExtract(factsheet, 'typeSpecification', 'maxLoadMass', 'Nullable(Float64)') AS max_load_kg,
            JSONExtract(factsheet, 'physicalParameters', 'speedMax', 'Nullable(Float64)') AS speed_max_m_s,
            JSONExtract(factsheet, 'physicalParameters', 'length', 'Nullable(Float64)') AS length_m,
            JSONExtract(factsheet, 'physicalParameters', 'width', 'Nullable(Float64)') AS width_m,
            factsheet
        FROM {db}.vda_factsheets FINAL""",
        {
            "robot_id": "The vehicle's robot id",
            "at": "The factsheet's timestamp (UTC, ms)",
            "vda_version": "The VDA 5050 version it was validated against",
            "manufacturer": "As the vehicle sent it",
            "serial_number": "As the vehicle sent it",
            "series_name": "typeSpecification.seriesName",
            "kinematic": "typeSpecification.agvKinematic (DIFF, OMNI, THREEWHEEL)",
            "vehicle_class": "typeSpecification.agvClass (FORKLIFT, CONVEYOR, TUGGER, CARRIER)",
            "max_load_kg": "typeSpecification.maxLoadMass in kg",
            "speed_max_m_s": "physicalParameters.speedMax in m/s",
            "length_m": "physicalParameters.length in metres",
            "width_m": "physicalParameters.width in metres",
            "factsheet": "The whole factsheet's JSON",
        },
    ),
}
