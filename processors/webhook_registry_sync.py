"""Keeps a processors replica's webhook deliveries (webhook_delivery.py) in step with the
registry operators edit through the API (mapservice/core/webhook_registry.py), and reports
back how they fare.

Every MAPSERVICE_WEBHOOK_REGISTRY_POLL_S a timer reads the registered webhooks, hands them
to the deliveries (a new one gets the next alerts, a removed one's queue is dropped, each
with its secret derived from the signing key), resumes those whose resume is newer than
the last this replica applied, and writes one report per webhook: its state, the pause's
reason, the last try, the counts. The reads and the report are small store calls on the
store thread; the deliveries themselves never wait for the store, nor the store for them.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Awaitable, Callable

import structlog

from mapservice.core.ports import WebhookRegistry
from mapservice.core.webhook_registry import WebhookReport
from mapservice.settings import Settings

from .webhook_delivery import DeliveryPolicy, WebhookDeliveries

log = structlog.get_logger(__name__)


def delivery_policy(settings: Settings) -> DeliveryPolicy:
    return DeliveryPolicy(
        timeout_s=settings.webhook_timeout_s,
        max_tries=settings.webhook_max_tries,
        backoff_cap_s=settings.webhook_backoff_cap_s,
        max_queued=settings.webhook_max_queued,
    )


def this_replica() -> str:
    """Names this process among the replicas (a restart is a new one: its counts start
    anew, and the old one's last report goes stale)."""
    return f"{socket.gethostname()}:{os.getpid()}"


class WebhookRegistrySync:
    def __init__(
        self,
        registry: WebhookRegistry,
        deliveries: WebhookDeliveries,
        signing_key: str,
        now_ms: Callable[[], int],
        replica: str | None = None,
    ) -> None:
        self.registry, self.deliveries = registry, deliveries
        self.signing_key, self.now_ms = signing_key, now_ms
        self.replica = replica or this_replica()
        # Per webhook, the resume time last seen: a later one is an operator's new resume.
        self._resumes: dict[str, int] = {}

    def sync(self) -> int:
        """Reads the registry, applies it, reports; returns how many webhooks are
        registered. Blocking: on the store thread."""
        webhooks = self.registry.webhooks()
        self.deliveries.set_webhooks(w.to_deliver(self.signing_key) for w in webhooks)
        resumes = {}
        for w in webhooks:
            seen = self._resumes.get(w.webhook_id)
            if seen is not None and w.resumed_ms > seen:
                self.deliveries.resume(w.webhook_id)
                log.info("webhook resumed", webhook=w.webhook_id)
            resumes[w.webhook_id] = w.resumed_ms
        self._resumes = resumes
        now = self.now_ms()
        self.registry.report_webhooks(
            [
                WebhookReport.of(
                    webhook_id, self.replica, now, health, self.deliveries.queued(webhook_id)
                )
                for webhook_id, health in self.deliveries.health().items()
            ]
        )
        return len(webhooks)

    async def tick(self, run: Callable[[Callable[[], int]], Awaitable[int]]) -> None:
        """One timer tick through `run` (the store thread's): a failure is logged and the
        next tick tries again, the deliveries going on as they were."""
        try:
            await run(self.sync)
        except Exception as exc:
            log.warning("webhook registry not read", error=str(exc)[:300])
