"""The pose tables' later layouts: the migrations that re-sort `poses` and its keyframes
(v4, v9), add the per-minute pose times and per-second chunk changes (v9), and move the pose
views behind the live push (v10); and the pose column list the reads and writes share.

Each function returns one migration's statements (schema.py numbers them); their text is
checksummed, so they change only by a new migration."""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema
from mapservice.adapters.clickhouse.table_comments import TABLE_COMMENTS_V9_KEYFRAMES

# The pose columns, in table order (the keyframe view and its backfill name them).
POSE_COLUMNS = (
    "robot_id, ts, x_mm, y_mm, z_mm, qx, qy, qz, qw, battery, charging, loaded, "
    "has_path, path_x_mm, path_y_mm, recv_lag_ms"
)
KEYFRAME_MS = 60_000  # one keyframe per robot per minute (pose_keyframes)

# One chunk_seconds row per second from chunk_events (FINAL): the sorted millisecond
# offsets of its writes (one per write; two writes in one millisecond repeat it).
CHUNK_SECONDS_SELECT = (
    "SELECT toDateTime(ts) AS second, "
    "arraySort(groupArray(toUInt16(toUnixTimestamp64Milli(ts) % 1000))), now64(3)"
)


def poses_by_time(db: str, ttl_days: int) -> tuple[str, ...]:
    """Schema v4 (bench timetravel, BENCHMARKS.md): every time-travel read of poses is a
    time window across robots (robots at T, replay windows, snapshots), so `poses` is
    re-sorted by (ts, robot_id): a window is one contiguous range of granules instead of
    one range per robot. The identity (robot, ts) is unchanged, so is deduplication.
    `pose_keyframes` holds each robot's first pose of every minute (a materialized view
    fills it on every insert into `poses`): a downsampled read whose start and step are
    whole minutes reads one row per robot per minute instead of every pose.

    Safe to run twice: the copy goes to `poses_v4` (deduplicated on its identity), the swap
    is one RENAME, the old table is dropped only once its rows are all in the new one.
    Writers must be stopped while it runs (the service migrates before its processors
    start); rows inserted into the old table during the copy would be lost.
    """
    return (
        # A run interrupted after the RENAME left the old table behind: its rows are in `poses`.
        f"DROP TABLE IF EXISTS {db}.poses_by_robot SYNC",
        # On a second run the view is re-created below on the new table (its backfill
        # covers whatever the view would have caught meanwhile).
        f"DROP VIEW IF EXISTS {db}.pose_keyframes_mv SYNC",
        f"""CREATE TABLE IF NOT EXISTS {db}.poses_v4 AS {db}.poses
            ENGINE = ReplacingMergeTree
            PARTITION BY toDate(ts)
            ORDER BY (ts, robot_id)
            TTL toDateTime(ts) + INTERVAL {ttl_days} DAY
            SETTINGS ttl_only_drop_parts = 1""",
        # Interleaved robots defeat Delta on positions; T64 (unused high bits cut per
        # block) keeps them at ~2 bytes. Gorilla gains nothing on quaternions in any order
        # and is the slowest codec to decode.
        *(
            f"ALTER TABLE {db}.poses_v4 MODIFY COLUMN {column} {kind} CODEC({codec})"
            for column, kind, codec in (
                ("x_mm", "Int32", "T64, ZSTD(3)"),
                ("y_mm", "Int32", "T64, ZSTD(3)"),
                ("z_mm", "Int32", "T64, ZSTD(3)"),
                ("qx", "Float32", "ZSTD(3)"),
                ("qy", "Float32", "ZSTD(3)"),
                ("qz", "Float32", "ZSTD(3)"),
                ("qw", "Float32", "ZSTD(3)"),
                ("battery", "Nullable(Float32)", "ZSTD(3)"),
            )
        ),
        f"INSERT INTO {db}.poses_v4 SELECT * FROM {db}.poses",
        f"RENAME TABLE {db}.poses TO {db}.poses_by_robot, {db}.poses_v4 TO {db}.poses",
        f"DROP TABLE IF EXISTS {db}.poses_by_robot SYNC",
        _keyframes_table(db, "pose_keyframes", "(robot_id, cell)", ttl_days),
        # Per insert block only the first pose per robot and minute: the bulk loader's
        # day-sized blocks shrink 60x before they are written.
        f"""CREATE MATERIALIZED VIEW IF NOT EXISTS {db}.pose_keyframes_mv TO {db}.pose_keyframes
            AS SELECT {POSE_COLUMNS} FROM {db}.poses
            ORDER BY robot_id, ts LIMIT 1 BY robot_id, toStartOfMinute(ts)""",
        (
            f"INSERT INTO {db}.pose_keyframes ({POSE_COLUMNS}) SELECT {POSE_COLUMNS} FROM {db}.poses "
            "ORDER BY robot_id, ts LIMIT 1 BY robot_id, toStartOfMinute(ts)"
        ),
    )


def _keyframes_table(db: str, name: str, order_by: str, ttl_days: int) -> str:
    """pose_keyframes' definition (schema v4), sorted by `order_by`.

    ReplacingMergeTree(rank): of the rows of one (robot, minute) the earliest pose has the
    highest rank; two writes of that pose keep the later one, as `poses` does."""
    return f"""CREATE TABLE IF NOT EXISTS {db}.{name} (
            robot_id LowCardinality(String),
            ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            x_mm Int32 CODEC(Delta, ZSTD(3)),
            y_mm Int32 CODEC(Delta, ZSTD(3)),
            z_mm Int32 CODEC(Delta, ZSTD(3)),
            qx Float32 CODEC(ZSTD(3)),
            qy Float32 CODEC(ZSTD(3)),
            qz Float32 CODEC(ZSTD(3)),
            qw Float32 CODEC(ZSTD(3)),
            battery Nullable(Float32) CODEC(ZSTD(3)),
            charging LowCardinality(String),
            loaded LowCardinality(String),
            has_path Bool,
            path_x_mm Array(Int32) CODEC(ZSTD(3)),
            path_y_mm Array(Int32) CODEC(ZSTD(3)),
            recv_lag_ms Int32 CODEC(T64, ZSTD(3)),
            cell DateTime('UTC') MATERIALIZED toStartOfMinute(ts),
            rank UInt32 MATERIALIZED toUInt32({KEYFRAME_MS} - toUnixTimestamp64Milli(ts) % {KEYFRAME_MS})
        ) ENGINE = ReplacingMergeTree(rank)
        PARTITION BY toDate(cell)
        ORDER BY {order_by}
        TTL cell + INTERVAL {ttl_days} DAY
        SETTINGS ttl_only_drop_parts = 1"""


def _pose_cells(
    db: str, name: str, start_of: str, ttl_days: int, source: str = "poses"
) -> tuple[str, str]:
    """A table of each robot's first and last pose time per cell (`start_of(ts)`: a minute,
    ten minutes), and the materialized view on `source` that fills it (schema v9: on
    `poses`; v10: on `pose_derivations`)."""
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.{name} (
            cell DateTime('UTC'),
            robot_id LowCardinality(String),
            first_ts SimpleAggregateFunction(min, DateTime64(3, 'UTC')) CODEC(DoubleDelta, ZSTD(3)),
            last_ts SimpleAggregateFunction(max, DateTime64(3, 'UTC')) CODEC(DoubleDelta, ZSTD(3))
        ) ENGINE = AggregatingMergeTree
        PARTITION BY toDate(cell)
        ORDER BY (cell, robot_id)
        TTL cell + INTERVAL {ttl_days} DAY
        SETTINGS ttl_only_drop_parts = 1""",
        f"""CREATE MATERIALIZED VIEW IF NOT EXISTS {db}.{name}_mv TO {db}.{name}
            AS SELECT {start_of}(ts) AS cell, robot_id, min(ts) AS first_ts, max(ts) AS last_ts
            FROM {db}.{source} GROUP BY cell, robot_id""",
    )


def replay_at_scale(db: str, ttl_days: int) -> tuple[str, ...]:
    """Schema v9 (time travel at 200 robots: BENCHMARKS.md).

    - `pose_keyframes` re-sorted by (cell, robot_id): every read of it is a time window
      across robots (downsampled replay windows, the timeline), which sorted by robot
      touched every granule of the table (each robot's week is about one granule), and can
      now be read in time order and stop at the LIMIT. Copied into `pose_keyframes_v9` and
      swapped in with one RENAME, as v4 did (safe to run twice; writers stopped).
    - `pose_minutes`: each robot's first and last pose time of every minute, a
      materialized view on `poses` (min/max, so unmerged rows and re-deliveries need no
      FINAL). For timeline buckets of a minute or more a robot has a pose in a bucket iff
      the first or the last pose of one of its minutes lies there, so "robots active per
      bucket" reads 2 values per robot-minute instead of every pose; `pose_ten_minutes`
      the same per ten minutes, for buckets of ten minutes or more.
    - `chunk_seconds`: the millisecond offsets of the chunk changes of every second,
      deduplicated (chunk_events FINAL). A materialized view cannot write it: it sees
      insert blocks, so a re-delivered write would count twice. The snapshot builders write
      it instead, for the seconds before each snapshot, and reads use it only before the
      newest valid snapshot (a late or re-delivered event notes a repair, as for the
      snapshots, and the repair rewrites it). Its rows hold the offsets, so timeline
      buckets that do not fall on whole seconds are still counted exactly, and their
      number (`changes`), which is all whole-second buckets read.
    """
    return (
        # A run interrupted after the RENAME left the old table behind.
        f"DROP TABLE IF EXISTS {db}.pose_keyframes_by_robot SYNC",
        f"DROP VIEW IF EXISTS {db}.pose_keyframes_mv SYNC",
        _keyframes_table(db, "pose_keyframes_v9", "(cell, robot_id)", ttl_days),
        (
            f"INSERT INTO {db}.pose_keyframes_v9 ({POSE_COLUMNS}) SELECT {POSE_COLUMNS} "
            f"FROM {db}.pose_keyframes FINAL"
        ),
        f"RENAME TABLE {db}.pose_keyframes TO {db}.pose_keyframes_by_robot, "
        f"{db}.pose_keyframes_v9 TO {db}.pose_keyframes",
        f"DROP TABLE IF EXISTS {db}.pose_keyframes_by_robot SYNC",
        f"""CREATE MATERIALIZED VIEW IF NOT EXISTS {db}.pose_keyframes_mv TO {db}.pose_keyframes
            AS SELECT {POSE_COLUMNS} FROM {db}.poses
            ORDER BY robot_id, ts LIMIT 1 BY robot_id, toStartOfMinute(ts)""",
        *_pose_cells(db, "pose_minutes", "toStartOfMinute", ttl_days),
        # Idempotent (min and max): a second run adds rows that change nothing.
        (
            f"INSERT INTO {db}.pose_minutes (cell, robot_id, first_ts, last_ts) "
            f"SELECT toStartOfMinute(ts) AS cell, robot_id, min(ts), max(ts) FROM {db}.poses "
            "GROUP BY cell, robot_id"
        ),
        # The same per ten minutes: a week's timeline reads a tenth of the rows.
        *_pose_cells(db, "pose_ten_minutes", "toStartOfTenMinutes", ttl_days),
        (
            f"INSERT INTO {db}.pose_ten_minutes (cell, robot_id, first_ts, last_ts) "
            f"SELECT toStartOfTenMinutes(cell) AS c, robot_id, min(first_ts), max(last_ts) "
            f"FROM {db}.pose_minutes GROUP BY c, robot_id"
        ),
        f"""CREATE TABLE IF NOT EXISTS {db}.chunk_seconds (
            second DateTime('UTC') CODEC(DoubleDelta, ZSTD(3)),
            offsets Array(UInt16) CODEC(ZSTD(3)),
            changes UInt32 MATERIALIZED length(offsets) CODEC(T64, ZSTD(3)),
            built DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3))
        ) ENGINE = ReplacingMergeTree(built)
        PARTITION BY toDate(second)
        ORDER BY second
        TTL second + INTERVAL {ttl_days} DAY
        SETTINGS ttl_only_drop_parts = 1""",
        # The seconds the existing snapshots cover (before the newest one), as they build it.
        (
            f"INSERT INTO {db}.chunk_seconds (second, offsets, built) {CHUNK_SECONDS_SELECT} "
            f"FROM {db}.chunk_events FINAL WHERE ts < (SELECT toDateTime(max(snap_ts)) "
            f"FROM {db}.snapshot_log) GROUP BY second"
        ),
        *analyst_schema.comment_statements(
            db,
            {
                **TABLE_COMMENTS_V9_KEYFRAMES,
                **analyst_schema.comments_of("pose_minutes", "pose_ten_minutes", "chunk_seconds"),
            },
        ),
    )


def pose_views_after_push(db: str, ttl_days: int) -> tuple[str, ...]:
    """Schema v10 (live latency at 1,000 robots: BENCHMARKS.md).

    The three pose views (pose_keyframes, pose_minutes, pose_ten_minutes) were materialized
    views on `poses`: every insert into it ran them, and they were most of its cost (a
    batch of poses took ~7 ms to insert without them, ~20-26 ms with them). A batch is
    pushed live once it is queryable, i.e. once `poses` holds it, so the views delayed every
    push. Now they read `pose_derivations`, a Null table (it keeps nothing) that the history
    consumer writes the same rows into after the push (`derive_views`), before it commits
    the batch's offsets: a crash in between re-delivers the batch, and the views' tables
    absorb the repeat as they did before (ReplacingMergeTree, min/max).

    The views' tables are complete when this runs (writers are stopped), so nothing is
    copied; safe to run twice (IF NOT EXISTS, and the views are dropped before each create).
    """
    return (
        f"CREATE TABLE IF NOT EXISTS {db}.pose_derivations AS {db}.poses ENGINE = Null",
        *(
            f"DROP VIEW IF EXISTS {db}.{view} SYNC"
            for view in ("pose_keyframes_mv", "pose_minutes_mv", "pose_ten_minutes_mv")
        ),
        f"""CREATE MATERIALIZED VIEW IF NOT EXISTS {db}.pose_keyframes_mv TO {db}.pose_keyframes
            AS SELECT {POSE_COLUMNS} FROM {db}.pose_derivations
            ORDER BY robot_id, ts LIMIT 1 BY robot_id, toStartOfMinute(ts)""",
        _pose_cells(db, "pose_minutes", "toStartOfMinute", ttl_days, "pose_derivations")[1],
        _pose_cells(db, "pose_ten_minutes", "toStartOfTenMinutes", ttl_days, "pose_derivations")[1],
        *analyst_schema.comment_statements(db, analyst_schema.comments_of("pose_derivations")),
    )
