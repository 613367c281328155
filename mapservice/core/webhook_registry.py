"""The webhooks operators registered for the incident alerts, as the store keeps them, and
how their deliveries fare, as the processors report them.

The API registers, removes and resumes webhooks (rows of the registry); every processors
replica re-reads the registry periodically and delivers to what it lists
(processors/webhook_registry_sync.py), so a change takes effect without a restart. A
replica's deliveries are its own (it sends the incidents it finds), so each replica
reports each webhook's state as a row of its own; `combined_state` folds the fresh ones into
what the API lists. A resume is a time in the registry's row: a replica resumes its paused
delivery when it sees a resume newer than the last one it applied.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import msgspec

from mapservice.core.webhooks import Webhook, WebhookHealth, derived_secret

WEBHOOK_ID = re.compile(r"wh-[0-9a-f]{16}")


class RegisteredWebhook(msgspec.Struct, frozen=True):
    """One webhook as registered: where to, which incident kinds (empty: all), who and when;
    `resumed_ms` the latest resume an operator asked for (0: none)."""

    webhook_id: str
    url: str
    kinds: tuple[str, ...]
    created_ms: int
    created_by: str
    resumed_ms: int = 0

    def to_deliver(self, signing_key: str) -> Webhook:
        """The webhook as the deliveries need it, with its derived secret."""
        return Webhook(
            self.webhook_id,
            self.url,
            derived_secret(signing_key, self.webhook_id),
            frozenset(self.kinds),
        )


class WebhookReport(msgspec.Struct, frozen=True):
    """One processors replica's deliveries to one webhook, as of `reported_ms` (the
    service's clock): its state and counts since that replica started."""

    webhook_id: str
    replica: str
    reported_ms: int
    paused_reason: str = ""
    last_error: str = ""
    last_try_ms: int = 0
    last_result: str = ""
    delivered: int = 0
    failed_tries: int = 0
    dropped: int = 0
    queued: int = 0

    @classmethod
    def of(
        cls, webhook_id: str, replica: str, now_ms: int, health: WebhookHealth, queued: int
    ) -> WebhookReport:
        return cls(
            webhook_id,
            replica,
            now_ms,
            health.paused_reason,
            health.last_error,
            health.last_try_ms,
            health.last_result,
            health.delivered,
            health.failed_tries,
            health.dropped,
            queued,
        )


class WebhookState(msgspec.Struct, frozen=True):
    """A webhook's deliveries over the replicas that reported lately: paused when one of
    them is (with its reason), the latest try, the counts summed."""

    state: str  # active | paused
    paused_reason: str
    last_try_ms: int | None
    last_result: str
    last_error: str
    delivered: int
    failed_tries: int
    dropped: int
    queued: int
    replicas: int  # how many replicas reported it lately (0: none yet, or none running)


def combined_state(reports: Sequence[WebhookReport], now_ms: int, fresh_ms: int) -> WebhookState:
    """The state of one webhook from its replicas' reports; a report older than `fresh_ms`
    is of a replica gone (restarted, scaled in) and left out."""
    fresh = [r for r in reports if r.reported_ms >= now_ms - fresh_ms]
    paused = [r for r in fresh if r.paused_reason]
    latest = max(fresh, key=lambda r: r.last_try_ms, default=None)
    failing = max((r for r in fresh if r.last_error), key=lambda r: r.last_try_ms, default=None)
    return WebhookState(
        state="paused" if paused else "active",
        paused_reason="; ".join(sorted({r.paused_reason for r in paused})),
        last_try_ms=latest.last_try_ms if latest is not None and latest.last_try_ms else None,
        last_result=latest.last_result if latest is not None else "",
        last_error=failing.last_error if failing is not None else "",
        delivered=sum(r.delivered for r in fresh),
        failed_tries=sum(r.failed_tries for r in fresh),
        dropped=sum(r.dropped for r in fresh),
        queued=sum(r.queued for r in fresh),
        replicas=len(fresh),
    )
