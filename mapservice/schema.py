"""The history's ClickHouse schema, as numbered migrations the service applies on start.

Choices, and why:
- ReplacingMergeTree on each event's natural identity (ORDER BY): a re-delivered batch
  leaves duplicates only until the next merge, and every read uses FINAL, so readers
  never see them.
- PARTITION BY day and TTL with ttl_only_drop_parts: expiry drops whole day-parts
  instead of rewriting them.
- Positions as Int32 millimetres with Delta+ZSTD, time as DoubleDelta: 1 Hz poses
  shrink to a few bytes a row. Chunk pixels live once per content hash per day in
  `chunk_contents`; chunk events reference them by a 16-byte hash.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Migration:
    version: int
    description: str
    statements: tuple[str, ...]


def migrations(database: str, retention_days: int) -> list[Migration]:
    ttl_days = int(retention_days)
    return [
        Migration(
            1,
            "history tables: poses, chunk events, chunk contents, map meta, dead letters",
            (
                f"""CREATE TABLE IF NOT EXISTS {database}.poses (
                    robot_id LowCardinality(String),
                    ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
                    x_mm Int32 CODEC(Delta, ZSTD(3)),
                    y_mm Int32 CODEC(Delta, ZSTD(3)),
                    z_mm Int32 CODEC(Delta, ZSTD(3)),
                    qx Float32 CODEC(Gorilla, ZSTD(3)),
                    qy Float32 CODEC(Gorilla, ZSTD(3)),
                    qz Float32 CODEC(Gorilla, ZSTD(3)),
                    qw Float32 CODEC(Gorilla, ZSTD(3)),
                    battery Nullable(Float32) CODEC(Gorilla, ZSTD(3)),
                    charging LowCardinality(String),
                    loaded LowCardinality(String),
                    has_path Bool,
                    path_x_mm Array(Int32) CODEC(ZSTD(3)),
                    path_y_mm Array(Int32) CODEC(ZSTD(3)),
                    recv_lag_ms Int32 CODEC(T64, ZSTD(3))
                ) ENGINE = ReplacingMergeTree
                PARTITION BY toDate(ts)
                ORDER BY (robot_id, ts)
                TTL toDateTime(ts) + INTERVAL {ttl_days} DAY
                SETTINGS ttl_only_drop_parts = 1""",
                f"""CREATE TABLE IF NOT EXISTS {database}.chunk_events (
                    ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
                    row UInt16 CODEC(ZSTD(3)),
                    col UInt16 CODEC(ZSTD(3)),
                    robot_id LowCardinality(String),
                    content_hash FixedString(16) CODEC(ZSTD(3)),
                    recv_lag_ms Int32 CODEC(T64, ZSTD(3))
                ) ENGINE = ReplacingMergeTree
                PARTITION BY toDate(ts)
                ORDER BY (ts, row, col, robot_id)
                TTL toDateTime(ts) + INTERVAL {ttl_days} DAY
                SETTINGS ttl_only_drop_parts = 1""",
                f"""CREATE TABLE IF NOT EXISTS {database}.chunk_contents (
                    content_hash FixedString(16),
                    day Date,
                    width UInt16,
                    height UInt16,
                    zlib_pixels String CODEC(NONE)
                ) ENGINE = ReplacingMergeTree
                PARTITION BY day
                ORDER BY content_hash
                TTL day + INTERVAL {ttl_days + 1} DAY
                SETTINGS ttl_only_drop_parts = 1""",
                f"""CREATE TABLE IF NOT EXISTS {database}.map_meta (
                    ts DateTime64(3, 'UTC'),
                    robot_id LowCardinality(String),
                    meta String
                ) ENGINE = ReplacingMergeTree
                ORDER BY (ts, robot_id)""",
                f"""CREATE TABLE IF NOT EXISTS {database}.dead_letters (
                    received DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
                    reason LowCardinality(String),
                    mqtt_topic String CODEC(ZSTD(3)),
                    detail String CODEC(ZSTD(3)),
                    payload String CODEC(ZSTD(3)),
                    gateway LowCardinality(String)
                ) ENGINE = MergeTree
                PARTITION BY toDate(received)
                ORDER BY (received, reason)
                TTL toDateTime(received) + INTERVAL {ttl_days} DAY
                SETTINGS ttl_only_drop_parts = 1""",
            ),
        ),
        Migration(
            2,
            "snapshots of the map and of each robot's latest pose, and their log",
            (
                f"""CREATE TABLE IF NOT EXISTS {database}.map_snapshots (
                    snap_ts DateTime64(3, 'UTC'),
                    row UInt16,
                    col UInt16,
                    ts DateTime64(3, 'UTC'),
                    robot_id LowCardinality(String),
                    content_hash FixedString(16),
                    built DateTime64(3, 'UTC')
                ) ENGINE = ReplacingMergeTree(built)
                PARTITION BY toDate(snap_ts)
                ORDER BY (snap_ts, row, col)
                TTL toDateTime(snap_ts) + INTERVAL {ttl_days + 1} DAY
                SETTINGS ttl_only_drop_parts = 1""",
                f"""CREATE TABLE IF NOT EXISTS {database}.robot_snapshots (
                    snap_ts DateTime64(3, 'UTC'),
                    robot_id LowCardinality(String),
                    ts DateTime64(3, 'UTC'),
                    built DateTime64(3, 'UTC')
                ) ENGINE = ReplacingMergeTree(built)
                PARTITION BY toDate(snap_ts)
                ORDER BY (snap_ts, robot_id)
                TTL toDateTime(snap_ts) + INTERVAL {ttl_days + 1} DAY
                SETTINGS ttl_only_drop_parts = 1""",
                f"""CREATE TABLE IF NOT EXISTS {database}.snapshot_log (
                    snap_ts DateTime64(3, 'UTC'),
                    built DateTime64(3, 'UTC'),
                    chunks UInt32,
                    robots UInt32
                ) ENGINE = ReplacingMergeTree(built)
                ORDER BY snap_ts
                TTL toDateTime(snap_ts) + INTERVAL {ttl_days + 1} DAY""",
            ),
        ),
    ]


SCHEMA_VERSION = 2
