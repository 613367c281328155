"""The history's ClickHouse schema, as numbered migrations the service applies on start.

Choices, and why:
- ReplacingMergeTree on each event's natural identity (ORDER BY): a re-delivered batch
  leaves duplicates only until the next merge, and every read uses FINAL, so readers
  never see them.
- PARTITION BY day: expiry drops whole day-parts instead of rewriting them.
- Positions as Int32 millimetres with Delta+ZSTD, time as DoubleDelta: 1 Hz poses
  shrink to a few bytes a row. Chunk pixels live once per content hash per day in
  `chunk_contents`; chunk events reference them by a 16-byte hash.

The later migrations' statements come from the module of their concern (the pose tables'
re-layouts: pose_schema.py; the analysts' comments and views: analyst_schema.py; VDA 5050,
annotations, commands, tracks, bursts, incidents, heatmaps, retention: their *_schema.py); this module numbers them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from mapservice.adapters.clickhouse import (
    analyst_schema,
    annotation_schema,
    burst_schema,
    command_schema,
    heatmap_schema,
    incident_schema,
    pose_schema,
    retention_schema,
    track_schema,
    vda_schema,
    vda_views,
    webhook_schema,
)


@dataclass(frozen=True)
class Migration:
    version: int
    description: str
    statements: tuple[str, ...]

    @property
    def checksum(self) -> str:
        """SHA-256 of the statements with whitespace collapsed (reformatting is no change).
        Compare `checksums()`, which renders every migration with fixed parameters."""
        text = "\n".join(" ".join(s.split()) for s in self.statements)
        return hashlib.sha256(text.encode()).hexdigest()


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
        Migration(
            3,
            "conflicts: two robots writing different content to one chunk within the window",
            (
                # Version ts_a: the rule is monotonic (mapservice/core/conflicts.py), so of two
                # rows with one identity the one naming the later A is the right one,
                # whatever order they were inserted in.
                f"""CREATE TABLE IF NOT EXISTS {database}.conflicts (
                    ts DateTime64(3, 'UTC'),
                    row UInt16,
                    col UInt16,
                    robot_a LowCardinality(String),
                    ts_a DateTime64(3, 'UTC'),
                    hash_a FixedString(16),
                    robot_b LowCardinality(String),
                    hash_b FixedString(16)
                ) ENGINE = ReplacingMergeTree(ts_a)
                PARTITION BY toDate(ts)
                ORDER BY (ts, row, col, robot_a, robot_b)
                TTL toDateTime(ts) + INTERVAL {ttl_days} DAY
                SETTINGS ttl_only_drop_parts = 1""",
            ),
        ),
        Migration(
            4,
            "poses sorted by (ts, robot_id); per-minute pose keyframes for downsampled reads",
            pose_schema.poses_by_time(database, ttl_days),
        ),
        Migration(
            5,
            "conflicts: one row per later write, without content hashes",
            _conflicts_per_write(database, ttl_days),
        ),
        Migration(
            6,
            "pose quaternions compressed with FPC before ZSTD",
            # Measured on the 1,000-robot load test (BENCHMARKS.md): qz and qw were ~60 % of
            # `poses` at ~3.6 bytes a value; FPC(20) + ZSTD stores them in ~2.95 (Gorilla:
            # 4.0). Parts written before keep their codec until a merge rewrites them.
            tuple(
                f"ALTER TABLE {database}.poses MODIFY COLUMN {q} Float32 CODEC(FPC(20), ZSTD(3))"
                for q in ("qx", "qy", "qz", "qw")
            ),
        ),
        Migration(
            7,
            "analysts: table and column comments; views in metres, degrees, booleans and UTC",
            analyst_schema.statements(database),
        ),
        Migration(
            8,
            "snapshot repairs: a late event invalidates snapshots; the timer rebuilds them in steps",
            (
                f"""CREATE TABLE IF NOT EXISTS {database}.snapshot_repairs (
                    from_ts DateTime64(3, 'UTC'),
                    noted DateTime64(3, 'UTC')
                ) ENGINE = MergeTree ORDER BY from_ts""",
                *analyst_schema.comment_statements(
                    database, analyst_schema.comments_of("snapshot_repairs")
                ),
            ),
        ),
        Migration(
            9,
            "replay at plant scale: keyframes sorted by time; per-minute pose times; "
            "per-second chunk changes",
            pose_schema.replay_at_scale(database, ttl_days),
        ),
        Migration(
            10,
            "pose views after the live push: the pose views read pose_derivations, written "
            "after a batch is stored and pushed",
            pose_schema.pose_views_after_push(database, ttl_days),
        ),
        Migration(
            11,
            "retention owned by the service: no ClickHouse TTL (it follows the real clock and "
            "dropped the floor's only writes); the retention step drops day partitions",
            retention_schema.statements(database, DAY_PARTITIONED),
        ),
        Migration(
            12,
            "VDA 5050 vehicles: states, errors, connections, factsheets",
            vda_schema.statements(database),
        ),
        Migration(
            13,
            "operators' annotations: points of interest and zones, as edit events",
            annotation_schema.statements(database),
        ),
        Migration(14, "commands to robots and their answers", command_schema.statements(database)),
        Migration(
            15,
            "analysts: keep-out violations with the zone's name (view)",
            tuple(analyst_schema.later_view_statements(database, "keep_out_violations")),
        ),
        Migration(
            16,
            "analysts: views of VDA 5050 vehicles' states, errors, connections, factsheets",
            analyst_schema.view_statements(database, vda_views.VIEWS),
        ),
        Migration(
            17,
            "pose_tracks: every pose sorted by robot, for one robot's plots and track",
            track_schema.statements(database, pose_schema.POSE_COLUMNS),
        ),
        Migration(
            18, "chunk_bursts: writers' dense 20 s, for uploads", burst_schema.statements(database)
        ),
        Migration(
            19,
            "incidents: near misses, stuck and silent robots, low batteries, as found",
            incident_schema.statements(database),
        ),
        Migration(
            20,
            "webhooks: the incident alerts' webhooks operators registered, and each "
            "processors replica's report of its deliveries",
            webhook_schema.statements(database),
        ),
        Migration(
            21,
            "heatmap_cells: per 10 minutes and 0.5 m cell the robots' samples, for heatmaps",
            heatmap_schema.statements(database),
        ),
        Migration(
            22,
            "incidents: the comments of the kinds found from the records beside the poses",
            incident_schema.kinds_comments(database),
        ),
    ]


def checksums() -> dict[int, str]:
    """Each migration's checksum, rendered for a fixed database name and retention: a
    migration's identity is its code, not the settings it was applied with."""
    return {m.version: m.checksum for m in migrations("db", 7)}


def _conflicts_per_write(db: str, ttl_days: int) -> tuple[str, ...]:
    """Schema v5 (BENCHMARKS.md, 1,000 robots): v3 kept one row per pair of conflicting
    robots with both content hashes, 5.9 MB per robot-day on the 2019 load test, where
    each write conflicts with several others. Now one row per later write (B's identity),
    naming the latest conflicting write; contents are joined from `chunk_events` on read.
    Version ts_a: the rule is monotonic (mapservice/core/conflicts.py), so of two rows with one
    identity the one naming the later A is right, whatever order they were inserted in.

    Safe to run twice, as v4: the copy goes to `conflicts_v5` (keeping per B the latest A
    of the old rows), the swap is one RENAME, the old table is dropped after it. The copy
    names its columns, so a re-run after the RENAME copies the new table onto itself.
    """
    return (
        f"DROP TABLE IF EXISTS {db}.conflicts_v3 SYNC",
        f"""CREATE TABLE IF NOT EXISTS {db}.conflicts_v5 (
            ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            row UInt16 CODEC(ZSTD(3)),
            col UInt16 CODEC(ZSTD(3)),
            robot_b LowCardinality(String),
            robot_a LowCardinality(String),
            ts_a DateTime64(3, 'UTC') CODEC(Delta, ZSTD(3))
        ) ENGINE = ReplacingMergeTree(ts_a)
        PARTITION BY toDate(ts)
        ORDER BY (ts, row, col, robot_b)
        TTL toDateTime(ts) + INTERVAL {ttl_days} DAY
        SETTINGS ttl_only_drop_parts = 1""",
        f"""INSERT INTO {db}.conflicts_v5 (ts, row, col, robot_b, robot_a, ts_a)
            SELECT ts, row, col, robot_b, argMax(robot_a, (ts_a, robot_a)), max(ts_a)
            FROM {db}.conflicts FINAL GROUP BY ts, row, col, robot_b""",
        f"RENAME TABLE {db}.conflicts TO {db}.conflicts_v3, {db}.conflicts_v5 TO {db}.conflicts",
        f"DROP TABLE IF EXISTS {db}.conflicts_v3 SYNC",
    )


SCHEMA_VERSION = 22

# Tables partitioned by day (toDate of their time column), whose TTL schema v11 removed;
# map_meta, snapshot_log and snapshot_repairs are not (retention.py deletes their old rows).
DAY_PARTITIONED = (
    "poses",
    "chunk_events",
    "chunk_contents",
    "dead_letters",
    "map_snapshots",
    "robot_snapshots",
    "conflicts",
    "pose_keyframes",
    "pose_minutes",
    "pose_ten_minutes",
    "chunk_seconds",
)
# Dropped by day by the retention step, older than the snapshot carrying the floor: those, and
# later tables (VDA 5050 facts but factsheets, zone violations, commands, tracks, bursts,
# incidents, heatmap cells).
RETAINED_BY_DAY = (
    *DAY_PARTITIONED,
    *vda_schema.RETAINED_BY_DAY,
    "zone_violations",
    "command_events",
    track_schema.TABLE,
    burst_schema.TABLE,
    incident_schema.TABLE,
    heatmap_schema.TABLE,
)
