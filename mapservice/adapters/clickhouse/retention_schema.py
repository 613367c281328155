"""Schema v11: retention owned by the service, not ClickHouse's TTL (its own module so
schema.py stays readable; schema.py lists the day-partitioned tables it is given)."""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema


def statements(db: str, day_partitioned: tuple[str, ...]) -> tuple[str, ...]:
    """Schema v11: every TTL removed; the service's retention step owns expiry.

    ClickHouse's TTL follows the server's real clock and knows nothing of what a row means:
    it dropped the day partition holding a map written once (the demo's floor, a wall
    unchanged for a week) before any snapshot carried it forward, and the pixels of
    contents every snapshot still named. The retention step (retention.py) first makes sure
    a snapshot at or before the retention boundary holds the floor, renews the contents any
    retained row names, then drops the day partitions older than that snapshot, by the
    service's clock (a simulated one in tests: the same code). Safe to run twice."""
    return (
        *(f"ALTER TABLE {db}.{table} REMOVE TTL" for table in (*day_partitioned, "snapshot_log")),
        # Each robot's last pose older than the kept days (a robot silent since), one row
        # per robot (the latest carried wins): robots_at reads it beside `poses`. One
        # partition (AS would copy the day partitions of `poses`, and rows of two days
        # never replace each other).
        f"""CREATE TABLE IF NOT EXISTS {db}.carried_poses AS {db}.poses
            ENGINE = ReplacingMergeTree(ts) PARTITION BY tuple() ORDER BY robot_id""",
        *analyst_schema.comment_statements(db, analyst_schema.comments_of("carried_poses")),
    )
