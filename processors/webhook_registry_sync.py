"""Keeps a processors replica's webhook deliveries (webhook_delivery.py) in step with the
registry operators edit through the API (mapservice/core/webhook_registry.py), and reports
back how they fare.

Every MAPSERVICE_WEBHOOK_REGISTRY_POLL_S a timer reads the registered webhooks, hands them
to the deliveries (a new one gets the next alerts, a removed one's queue is dropped, each
with its secret derived from the signing key), resumes those whose resume is newer than
the last this replica applied, and writes one report per webhook: its state, the pause's
reason, the last try, the counts. Reports are written when they changed, and all of them
at least every `heartbeat_ms` (20 s), so the API can tell a replica gone (no report for a
minute) without an insert every poll. The reads and the report are small store calls on
the store thread; the deliveries themselves never wait for the store, nor the store for
them.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Awaitable, Callable

import msgspec
import structlog

from mapservice.adapters.webhook_destinations import destination_policy
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
        destinations=destination_policy(settings),
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
        heartbeat_ms: int = 20_000,
    ) -> None:
        self.registry, self.deliveries = registry, deliveries
        self.signing_key, self.now_ms = signing_key, now_ms
        self.replica = replica or this_replica()
        self.heartbeat_ms = heartbeat_ms
        # Per webhook, the resume time last seen: a later one is an operator's new resume.
        self._resumes: dict[str, int] = {}
        # What was last written (its time left out), and when everything was.
        self._reported: dict[str, WebhookReport] = {}
        self._all_reported_ms: int | None = None

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
        self._report(self.now_ms())
        return len(webhooks)

    def _report(self, now: int) -> None:
        reports = {
            webhook_id: WebhookReport.of(
                webhook_id, self.replica, 0, health, self.deliveries.queued(webhook_id)
            )
            for webhook_id, health in self.deliveries.health().items()
        }
        due = self._all_reported_ms is None or now - self._all_reported_ms >= self.heartbeat_ms
        changed = [r for k, r in reports.items() if due or self._reported.get(k) != r]
        if changed:
            self.registry.report_webhooks(
                [msgspec.structs.replace(r, reported_ms=now) for r in changed]
            )
        self._reported = reports
        if due:
            self._all_reported_ms = now

    async def tick(self, run: Callable[[Callable[[], int]], Awaitable[int]]) -> None:
        """One timer tick through `run` (the store thread's): a failure is logged and the
        next tick tries again, the deliveries going on as they were."""
        try:
            await run(self.sync)
        except Exception as exc:
            log.warning("webhook registry not read", error=str(exc)[:300])
