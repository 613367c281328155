"""The memory store's webhooks registry: each webhook's latest saved row and each replica's
latest report, as ClickHouse's `webhooks` and `webhook_reports` read with FINAL keep them
(mapservice/adapters/clickhouse/webhook_schema.py)."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from mapservice.core.webhook_registry import RegisteredWebhook, WebhookReport


class WebhookLog:
    def __init__(self) -> None:
        # id -> (changed_ms, the webhook or None once removed): the latest row
        self._rows: dict[str, tuple[int, RegisteredWebhook | None]] = {}
        self._reports: dict[tuple[str, str], WebhookReport] = {}
        self._lock = threading.Lock()

    def _save(self, webhook_id: str, changed_ms: int, webhook: RegisteredWebhook | None) -> None:
        with self._lock:
            before = self._rows.get(webhook_id)
            # As ReplacingMergeTree(changed): the later row, on a tie the later insert
            if before is None or changed_ms >= before[0]:
                self._rows[webhook_id] = (changed_ms, webhook)

    def save_webhook(self, webhook: RegisteredWebhook, changed_ms: int) -> None:
        self._save(webhook.webhook_id, changed_ms, webhook)

    def remove_webhook(self, webhook_id: str, changed_ms: int) -> None:
        self._save(webhook_id, changed_ms, None)

    def webhooks(self) -> list[RegisteredWebhook]:
        with self._lock:
            found = [w for _, w in self._rows.values() if w is not None]
        return sorted(found, key=lambda w: (w.created_ms, w.webhook_id))

    def report_webhooks(self, reports: Sequence[WebhookReport]) -> None:
        with self._lock:
            for r in reports:
                key = (r.webhook_id, r.replica)
                before = self._reports.get(key)
                if before is None or r.reported_ms >= before.reported_ms:
                    self._reports[key] = r

    def webhook_reports(self) -> list[WebhookReport]:
        with self._lock:
            return [self._reports[k] for k in sorted(self._reports)]
