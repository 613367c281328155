"""Schema v20: the webhooks operators registered for the incident alerts, and each
processors replica's report of its deliveries to them (mapservice/core/webhook_registry.py).

State, not history: neither table is partitioned by day nor touched by the retention.
`webhooks` keeps one row per webhook, the latest saved (ReplacingMergeTree versioned by
`changed`; a removal is a row of its own with `removed`); no secret is stored (each is
derived from the service's signing key). `webhook_reports` keeps each replica's latest
report per webhook; a replica gone leaves its last report, which the API ignores once it
is stale.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse import analyst_schema

WEBHOOKS = "webhooks"
REPORTS = "webhook_reports"
WEBHOOK_COLUMNS = (
    "webhook_id",
    "url",
    "kinds",
    "created",
    "created_by",
    "resumed",
    "removed",
    "changed",
)
REPORT_COLUMNS = (
    "webhook_id",
    "replica",
    "reported",
    "paused_reason",
    "last_error",
    "last_try",
    "last_result",
    "delivered",
    "failed_tries",
    "dropped",
    "queued",
)


def statements(db: str) -> tuple[str, ...]:
    return (
        f"""CREATE TABLE IF NOT EXISTS {db}.{WEBHOOKS} (
            webhook_id String,
            url String,
            kinds Array(LowCardinality(String)),
            created DateTime64(3, 'UTC'),
            created_by String,
            resumed DateTime64(3, 'UTC'),
            removed Bool,
            changed DateTime64(3, 'UTC')
        ) ENGINE = ReplacingMergeTree(changed)
        ORDER BY webhook_id""",
        f"""CREATE TABLE IF NOT EXISTS {db}.{REPORTS} (
            webhook_id String,
            replica String,
            reported DateTime64(3, 'UTC'),
            paused_reason String,
            last_error String,
            last_try DateTime64(3, 'UTC'),
            last_result String,
            delivered UInt64,
            failed_tries UInt64,
            dropped UInt64,
            queued UInt64
        ) ENGINE = ReplacingMergeTree(reported)
        ORDER BY (webhook_id, replica)""",
        *analyst_schema.comment_statements(db, analyst_schema.comments_of(WEBHOOKS, REPORTS)),
    )
