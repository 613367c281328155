"""Schema v19: `incidents`, what went wrong on the floor as the processors found it
(mapservice/core/incidents.py), one row per finding.

An incident is found again as its history grows (a robot still stuck, its end later) or
changes (a late pose breaks it: the finding retracts it): ReplacingMergeTree on its
identity, versioned by when it was found, keeps the latest finding; reads use FINAL and
leave retracted ones out. Keyed by start (the id is a digest of kind, robots and start, so
an incident's findings share their start, and so their partition). Partitioned by the
start's day and dropped by day with the rest of the history (schema.RETAINED_BY_DAY).
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema
from mapservice.adapters.clickhouse.table_comments import INCIDENTS_V19_COMMENTS

TABLE = "incidents"
COLUMNS = (
    "incident_id",
    "kind",
    "robots",
    "start",
    "end",
    "ongoing",
    "x",
    "y",
    "severity",
    "measure",
    "evidence",
    "found",
    "retracted",
)


def statements(db: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.{TABLE} (
            incident_id String,
            kind LowCardinality(String),
            robots Array(LowCardinality(String)),
            start DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)),
            end DateTime64(3, 'UTC') CODEC(Delta, ZSTD(3)),
            ongoing Bool,
            x Float64,
            y Float64,
            severity LowCardinality(String),
            measure Float64,
            evidence String CODEC(ZSTD(3)),
            found DateTime64(3, 'UTC') CODEC(Delta, ZSTD(3)),
            retracted Bool
        ) ENGINE = ReplacingMergeTree(found)
        PARTITION BY toDate(start)
        ORDER BY (start, kind, incident_id)""",
        *analyst_schema.comment_statements(db, INCIDENTS_V19_COMMENTS),
    )


def kinds_comments(db: str) -> tuple[str, ...]:
    """Migration 22: the incidents table's comments for every kind found."""
    return tuple(analyst_schema.comment_statements(db, analyst_schema.comments_of(TABLE)))
