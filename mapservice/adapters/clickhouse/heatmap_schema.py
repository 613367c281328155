"""Schema v21: `heatmap_cells`, per 10-minute bucket and finest cell (0.5 m) the sums the
heatmaps need (mapservice/core/heatmaps.py has the rule): samples, still samples, known
speeds and their sum. A week's heatmap reads a few rows per cell and bucket instead of
every pose of the week, and a coarser cell sums whole finest cells.

A materialized view cannot write it: it sees insert blocks, so a re-delivered batch would
count twice, and a sample's speed needs the robot's previous sample, often in an earlier
block. The snapshot builders write it instead, as `chunk_bursts` (schema v18): each build
the whole buckets before its snapshot since the previous one, from poses FINAL (looking
back one offline threshold for the previous samples), and reads use it only before the
newest valid snapshot; the partial buckets at a span's ends and the time after that
snapshot (at most a snapshot interval) are read from the poses by the same rule. A late
pose's repair rebuilds the buckets after it (ReplacingMergeTree(built): the rebuilt rows
replace the old). Backfilled once for the existing snapshots with the default thresholds;
safe to run twice. Partitioned by day and dropped by day with the rest of the history
(schema.RETAINED_BY_DAY).
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema
from mapservice.core.heatmaps import BUCKET_MS as BUCKET_MS
from mapservice.core.heatmaps import FINEST_CELL_MM, SAMPLE_MS, HeatmapRule

TABLE = "heatmap_cells"
BUCKET_S = BUCKET_MS // 1000
COLUMNS = ("bucket", "i", "j", "samples", "still", "speeds", "speed_sum", "built")


def samples_select(db: str, lo: str, hi: str, rule: HeatmapRule) -> str:
    """Every sample whose second starts in [lo, hi) (SQL expressions in epoch ms; poses
    before hi), with its robot's previous sample: columns t, x, y (mm), `known` (a previous
    sample within the offline threshold), `still` and `speed` (m/s)."""
    d2 = "(x - px) * (x - px) + (y - py) * (y - py)"
    reach = f"({float(rule.moving_m_s)!r} * (t - pt))"
    return (
        f"SELECT t, x, y, n > 1 AND t - pt <= {int(rule.offline_after_ms)} AS known, "
        f"{d2} < {reach} * {reach} AS still, sqrt({d2}) / (t - pt) AS speed "
        "FROM (SELECT t, x, y, row_number() OVER w AS n, lagInFrame(t) OVER w AS pt, "
        "lagInFrame(x) OVER w AS px, lagInFrame(y) OVER w AS py "
        "FROM (SELECT robot_id, toUnixTimestamp64Milli(ts) AS t, x_mm AS x, y_mm AS y "
        f"FROM {db}.poses FINAL PREWHERE ts >= fromUnixTimestamp64Milli("
        f"intDiv({lo}, {SAMPLE_MS}) * {SAMPLE_MS} - {rule.lookback_ms}) "
        f"AND ts < fromUnixTimestamp64Milli({hi}) "
        f"ORDER BY robot_id, t LIMIT 1 BY robot_id, intDiv(t, {SAMPLE_MS})) "
        "WINDOW w AS (PARTITION BY robot_id ORDER BY t ROWS BETWEEN 1 PRECEDING AND CURRENT ROW)) "
        f"WHERE intDiv(t, {SAMPLE_MS}) * {SAMPLE_MS} >= {lo}"
    )


# The sums of a group of samples (a select of `samples_select` grouped by cell).
SUMS = "count() AS samples, countIf(known AND still) AS still_n, countIf(known) AS speeds, sumIf(speed, known) AS speed_sum"
CELL_I = f"toInt32(floor(x / {FINEST_CELL_MM}))"
CELL_J = f"toInt32(floor(y / {FINEST_CELL_MM}))"


def buckets_insert(db: str, lo: str, hi: str, rule: HeatmapRule) -> str:
    """The rows of the whole buckets in [lo, hi) (bucket edges), as inserted."""
    return (
        f"INSERT INTO {db}.{TABLE} ({', '.join(COLUMNS)}) "
        f"SELECT toDateTime(intDiv(t, {BUCKET_MS}) * {BUCKET_S}) AS bucket, {CELL_I} AS i, "
        f"{CELL_J} AS j, {SUMS}, now64(3) FROM ({samples_select(db, lo, hi, rule)}) "
        "GROUP BY bucket, i, j"
    )


def statements(db: str) -> tuple[str, ...]:
    newest = (
        f"(SELECT intDiv(toUnixTimestamp64Milli(max(snap_ts)), {BUCKET_MS}) * {BUCKET_MS} "
        f"FROM {db}.snapshot_log)"
    )
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.{TABLE} (
            bucket DateTime('UTC') CODEC(DoubleDelta, ZSTD(3)),
            i Int32 CODEC(T64, ZSTD(3)),
            j Int32 CODEC(T64, ZSTD(3)),
            samples UInt32 CODEC(T64, ZSTD(3)),
            still UInt32 CODEC(T64, ZSTD(3)),
            speeds UInt32 CODEC(T64, ZSTD(3)),
            speed_sum Float64 CODEC(ZSTD(3)),
            built DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3))
        ) ENGINE = ReplacingMergeTree(built)
        PARTITION BY toDate(bucket)
        ORDER BY (bucket, i, j)""",
        # The whole buckets before the newest snapshot, as its builds would have written them.
        buckets_insert(db, "0", newest, HeatmapRule()),
        *analyst_schema.comment_statements(db, analyst_schema.comments_of(TABLE)),
    )
