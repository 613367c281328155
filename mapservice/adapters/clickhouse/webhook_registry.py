"""The webhooks registry (schema v20): `ClickHouseWebhookRegistry`, the WebhookRegistry
role, over the store's connection. Saves and reports are small inserts on the writer
client; reads use FINAL, so the latest row of each webhook (and of each replica's report)
is the one read."""

from __future__ import annotations

from collections.abc import Sequence

from mapservice.adapters.clickhouse import webhook_schema
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.webhook_registry import RegisteredWebhook, WebhookReport

_WEBHOOK = (
    "webhook_id, url, kinds, toUnixTimestamp64Milli(created), created_by, "
    "toUnixTimestamp64Milli(resumed)"
)
_REPORT = (
    "webhook_id, replica, toUnixTimestamp64Milli(reported), paused_reason, last_error, "
    "toUnixTimestamp64Milli(last_try), last_result, delivered, failed_tries, dropped, queued"
)


class ClickHouseWebhookRegistry:
    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def save_webhook(self, webhook: RegisteredWebhook, changed_ms: int) -> None:
        w = webhook
        row = [
            w.webhook_id,
            w.url,
            list(w.kinds),
            w.created_ms,
            w.created_by,
            w.resumed_ms,
            False,
            changed_ms,
        ]
        self._insert(webhook_schema.WEBHOOKS, [row], webhook_schema.WEBHOOK_COLUMNS)

    def remove_webhook(self, webhook_id: str, changed_ms: int) -> None:
        row = [webhook_id, "", [], 0, "", 0, True, changed_ms]
        self._insert(webhook_schema.WEBHOOKS, [row], webhook_schema.WEBHOOK_COLUMNS)

    def webhooks(self) -> list[RegisteredWebhook]:
        rows = self.connection.rows(
            f"SELECT {_WEBHOOK} FROM {self.connection.database}.{webhook_schema.WEBHOOKS} "
            "FINAL WHERE NOT removed ORDER BY created, webhook_id",
            {},
        )
        return [
            RegisteredWebhook(i, url, tuple(kinds), int(created), by, int(resumed))
            for i, url, kinds, created, by, resumed in rows
        ]

    def report_webhooks(self, reports: Sequence[WebhookReport]) -> None:
        rows = [
            [
                r.webhook_id,
                r.replica,
                r.reported_ms,
                r.paused_reason,
                r.last_error,
                r.last_try_ms,
                r.last_result,
                r.delivered,
                r.failed_tries,
                r.dropped,
                r.queued,
            ]
            for r in reports
        ]
        if rows:
            self._insert(webhook_schema.REPORTS, rows, webhook_schema.REPORT_COLUMNS)

    def webhook_reports(self) -> list[WebhookReport]:
        rows = self.connection.rows(
            f"SELECT {_REPORT} FROM {self.connection.database}.{webhook_schema.REPORTS} "
            "FINAL ORDER BY webhook_id, replica",
            {},
        )
        return [
            WebhookReport(w, replica, int(at), paused, error, int(tried), result, *map(int, counts))
            for w, replica, at, paused, error, tried, result, *counts in rows
        ]

    def _insert(self, table: str, rows: list[list[object]], columns: Sequence[str]) -> None:
        with self.connection.lock:
            self.connection.insert(table, rows, list(columns))
