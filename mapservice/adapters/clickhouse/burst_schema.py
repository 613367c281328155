"""Schema v18: `chunk_bursts`, per writer and 20 s bucket the count of its chunk writes,
kept only where the count could be part of a map upload (mapservice/core/upload_scan.py),
so a week's upload marks read a few rows, not every write of the week.

A materialized view cannot write it (it sees insert blocks: a burst split over two blocks
would count short in both, and a count is kept or dropped on its whole bucket). The
snapshot builders write it instead, as `chunk_seconds` (schema v9): each build the whole
buckets before its snapshot since the previous one, from chunk_events FINAL, and reads use
it only before the newest valid snapshot (the buckets after it come from chunk_events, a
snapshot interval of writes). A late event's repair rebuilds the snapshots after it and
these rows with them (ReplacingMergeTree(built): the rebuilt count replaces the old).
Backfilled once for the existing snapshots; safe to run twice. Partitioned by day and
dropped by day with the rest of the history (schema.RETAINED_BY_DAY).
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema
from mapservice.core.change_feed import UPLOADER_ID
from mapservice.core.upload_scan import BURST_BUCKET_MS, BURST_MIN_WRITES

TABLE = "chunk_bursts"
BUCKET_S = BURST_BUCKET_MS // 1000
assert BUCKET_S * 1000 == BURST_BUCKET_MS  # buckets of whole seconds: a DateTime column

# The buckets of chunk_events rows (add FROM and a filter on ts) worth keeping, as inserted.
BURSTS_SELECT = (
    f"SELECT toStartOfInterval(ts, INTERVAL {BUCKET_S} SECOND) AS bucket, robot_id, "
    "toUInt32(count()) AS writes, now64(3)"
)
BURSTS_KEPT = (
    f"GROUP BY bucket, robot_id HAVING writes >= {BURST_MIN_WRITES} OR robot_id = '{UPLOADER_ID}'"
)


def statements(db: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.{TABLE} (
            bucket DateTime('UTC') CODEC(DoubleDelta, ZSTD(3)),
            robot_id LowCardinality(String),
            writes UInt32 CODEC(T64, ZSTD(3)),
            built DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3))
        ) ENGINE = ReplacingMergeTree(built)
        PARTITION BY toDate(bucket)
        ORDER BY (bucket, robot_id)""",
        # The whole buckets before the newest snapshot, as its builds would have written them.
        (
            f"INSERT INTO {db}.{TABLE} (bucket, robot_id, writes, built) {BURSTS_SELECT} "
            f"FROM {db}.chunk_events FINAL WHERE ts < (SELECT toStartOfInterval(max(snap_ts), "
            f"INTERVAL {BUCKET_S} SECOND) FROM {db}.snapshot_log) {BURSTS_KEPT}"
        ),
        *analyst_schema.comment_statements(db, analyst_schema.comments_of(TABLE)),
    )
