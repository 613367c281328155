"""Schema v17: `pose_tracks`, every pose again, sorted by (robot_id, ts), for the reads of
one robot over a window (the plot panel's battery, speed and distance, GET .../track).

`poses` is sorted by (ts, robot_id) (schema v4), right for every read across robots at an
instant or in a window; but one robot's hour there is one granule range holding every
robot's hour, so a plot of one robot read 200 robots' poses (FINAL) to keep 1/200 of them:
p95 2.5 s for a 1 h plot on a 200-robot day. Sorted by robot, the same read is one
contiguous range of that robot's granules, and positions compress with Delta again as in
schema v1 (consecutive rows are one robot's consecutive poses).

Filled like the other pose views by a materialized view on `pose_derivations` (schema v10),
so a batch is pushed live before it is written here; backfilled from `poses` once.
ReplacingMergeTree on the pose's identity, as `poses`: a re-delivered batch and a second
run of the backfill leave duplicates only until merged, and reads use FINAL. Safe to run
twice (IF NOT EXISTS; the view is dropped before it is created).
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema

TABLE = "pose_tracks"


def statements(db: str, pose_columns: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.{TABLE} AS {db}.poses
            ENGINE = ReplacingMergeTree
            PARTITION BY toDate(ts)
            ORDER BY (robot_id, ts)""",
        # One robot's consecutive positions differ by millimetres: Delta shrinks them
        # (poses, interleaving robots, needed T64).
        *(
            f"ALTER TABLE {db}.{TABLE} MODIFY COLUMN {c} Int32 CODEC(Delta, ZSTD(3))"
            for c in ("x_mm", "y_mm", "z_mm")
        ),
        f"DROP VIEW IF EXISTS {db}.{TABLE}_mv SYNC",
        f"""CREATE MATERIALIZED VIEW IF NOT EXISTS {db}.{TABLE}_mv TO {db}.{TABLE}
            AS SELECT {pose_columns} FROM {db}.pose_derivations""",
        f"INSERT INTO {db}.{TABLE} ({pose_columns}) SELECT {pose_columns} FROM {db}.poses",
        *analyst_schema.comment_statements(db, analyst_schema.comments_of(TABLE)),
    )
