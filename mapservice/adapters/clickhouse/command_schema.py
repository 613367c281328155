"""Schema v14: operators' commands to robots and the robots' answers, as events.

One row per event: a command issued (who, which robot, what), a robot's ack and its
outcome. History, not state: partitioned by day and dropped with the retention like the
poses. ReplacingMergeTree on the event's identity: a redelivered event is stored once.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema

COLUMNS = (
    "ts",
    "robot_id",
    "command_id",
    "event",
    "event_id",
    "kind",
    "status",
    "by",
    "poi_id",
    "x",
    "y",
    "heading",
    "reason",
)


def statements(db: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.command_events (
            ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            robot_id LowCardinality(String),
            command_id String,
            event LowCardinality(String),
            event_id String,
            kind LowCardinality(String),
            status LowCardinality(String),
            by String,
            poi_id String,
            x Nullable(Float64),
            y Nullable(Float64),
            heading Nullable(Float64),
            reason String
        ) ENGINE = ReplacingMergeTree PARTITION BY toDate(ts)
          ORDER BY (ts, robot_id, command_id, event_id)""",
        *analyst_schema.comment_statements(db, analyst_schema.comments_of("command_events")),
    )
