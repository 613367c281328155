"""Schema v12: the facts of VDA 5050 vehicles beyond their poses (which `poses` holds).

A vehicle's robot id is `<manufacturer>:<serialNumber>` escaped (ingest/vda5050.py); the
tables keep both names as sent. ReplacingMergeTree on each fact's identity: a redelivered
message (QoS 1) is stored once.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema

TABLE_COMMENTS: dict[str, tuple[str, dict[str, str]]] = {
    "vda_states": ("VDA 5050 vehicle states (and visualizations off the known maps): status "
                   "and position as reported, in the vehicle's map frame", {
        "map_id": "the vehicle's mapId; NULL when it reported no position",
        "on_known_map": "true when mapId has a transform (its pose is in `poses`); false: "
                        "flagged, not drawn",
        "x": "metres in the vehicle's mapId frame, as reported",
        "theta": "radians in the vehicle's mapId frame, as reported",
        "operating_mode": "AUTOMATIC, SEMIAUTOMATIC, MANUAL, SERVICE, TEACHIN",
    }),
    "vda_errors": ("VDA 5050 errors and warnings, one row per error active in a state", {
        "level": "WARNING or FATAL (3.0: also URGENT, CRITICAL)",
    }),
    "vda_connections": ("VDA 5050 connection states: exact online/offline instants", {
        "ts": "when the state holds: the message time, or for CONNECTIONBROKEN (the last "
              "will, composed at connect time) when the gateway received it",
        "sent_ts": "the message's own timestamp",
    }),
    "vda_factsheets": ("VDA 5050 factsheets, as the vehicle sent them (JSON)", {}),
}


def statements(db: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.vda_states (
            robot_id LowCardinality(String),
            ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            manufacturer LowCardinality(String),
            serial_number LowCardinality(String),
            vda_version LowCardinality(String),
            map_id Nullable(String),
            on_known_map Bool,
            x Nullable(Float64),
            y Nullable(Float64),
            theta Nullable(Float64),
            driving Nullable(Bool),
            paused Nullable(Bool),
            operating_mode LowCardinality(String),
            order_id String,
            error_count UInt16
        ) ENGINE = ReplacingMergeTree PARTITION BY toDate(ts) ORDER BY (robot_id, ts)""",
        f"""CREATE TABLE IF NOT EXISTS {db}.vda_errors (
            robot_id LowCardinality(String),
            ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            level LowCardinality(String),
            type LowCardinality(String),
            description String
        ) ENGINE = ReplacingMergeTree PARTITION BY toDate(ts)
        ORDER BY (robot_id, ts, level, type, description)""",
        f"""CREATE TABLE IF NOT EXISTS {db}.vda_connections (
            robot_id LowCardinality(String),
            ts DateTime64(3, 'UTC'),
            state LowCardinality(String),
            sent_ts DateTime64(3, 'UTC')
        ) ENGINE = ReplacingMergeTree PARTITION BY toDate(ts) ORDER BY (robot_id, ts, state)""",
        f"""CREATE TABLE IF NOT EXISTS {db}.vda_factsheets (
            robot_id LowCardinality(String),
            ts DateTime64(3, 'UTC'),
            vda_version LowCardinality(String),
            factsheet String CODEC(ZSTD(3))
        ) ENGINE = ReplacingMergeTree ORDER BY (robot_id, ts)""",
        *analyst_schema.comment_statements(db, TABLE_COMMENTS),
    )
