"""Schema v13: operators' annotations (points of interest, zones) as their edit events.

One row per event (created, changed, removed), its content as the JSON the API speaks.
Not partitioned by day: annotations are state, and the retention step (retention.py)
keeps, of the edits before the retention boundary, those that make the annotations
standing at the boundary; the later ones are the kept history. ReplacingMergeTree on the
event's identity: a redelivered event is stored once.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema


def statements(db: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.annotation_events (
            annotation_id String,
            ts DateTime64(3, 'UTC'),
            event_id String,
            change LowCardinality(String),
            author String,
            shape LowCardinality(String),
            kind LowCardinality(String),
            name String,
            body String CODEC(ZSTD(3))
        ) ENGINE = ReplacingMergeTree ORDER BY (annotation_id, ts, event_id)""",
        f"""CREATE TABLE IF NOT EXISTS {db}.zone_violations (
            ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            robot_id LowCardinality(String),
            annotation_id String,
            x Float64,
            y Float64
        ) ENGINE = ReplacingMergeTree PARTITION BY toDate(ts) ORDER BY (ts, robot_id, annotation_id)""",
        *analyst_schema.comment_statements(
            db, analyst_schema.comments_of("annotation_events", "zone_violations")
        ),
    )
