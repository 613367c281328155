"""Schema v12: the facts of VDA 5050 vehicles beyond their poses (which `poses` holds).

A vehicle's robot id is `<manufacturer>:<serialNumber>` escaped (ingest/vda5050.py); the
tables keep both names as sent. ReplacingMergeTree on each fact's identity: a redelivered
message (QoS 1) is stored once.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema

# Dropped by day with the retention (factsheets are kept: one a vehicle, its latest matters).
RETAINED_BY_DAY = ("vda_states", "vda_errors", "vda_connections")


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
        *analyst_schema.comment_statements(
            db,
            analyst_schema.comments_of(
                "vda_states", "vda_errors", "vda_connections", "vda_factsheets"
            ),
        ),
    )
