"""Delivers incident alerts to the registered webhooks, off the pipeline: `offer` only
queues (a lock held for a few appends) and returns; worker threads of their own POST the
alerts with httpx, signed (mapservice/core/webhooks.py), so a receiver that is slow, down or
wrong costs the processors nothing but queue space.

Each webhook has its own queue, sent oldest first, one delivery at a time: a receiver
that fails gets one try per backoff step (1 s, 2 s, 4 s ... up to the cap), not one per
queued alert. A delivery that failed every one of its tries pauses its webhook (why is
kept for the API to show); its deliveries then wait until an operator resumes it. The
queues together hold at most `max_queued` deliveries: past that the oldest is dropped and
counted (`mapservice_webhook_deliveries_total{result="dropped"}`), so an alert storm or a
long pause holds memory bounded.

At least once, within a process's life: a delivery is retried until its receiver answers
2xx (a receiver may get one twice, when its answer was lost: `X-Mapservice-Delivery`
names each delivery). What is queued when the process stops is not sent; the incidents
themselves are stored and listed by the API.
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import httpx
import msgspec
import structlog
from prometheus_client import Counter, Gauge

from mapservice.adapters.webhook_destinations import DestinationPolicy, guarded_client, try_within
from mapservice.core.webhooks import (
    DELIVERY_HEADER,
    WEBHOOK_ID_HEADER,
    Webhook,
    WebhookHealth,
    backoff_s,
    signed_headers,
)

log = structlog.get_logger(__name__)

DELIVERIES = Counter(
    "mapservice_webhook_deliveries_total",
    "Webhook deliveries of incident alerts: delivered, a try that failed, dropped (queue full)",
    ["result"],
)
QUEUED = Gauge("mapservice_webhook_queued", "Webhook deliveries waiting to be sent")

_json = msgspec.json.Encoder()


@dataclass
class _Delivery:
    seq: int
    delivery_id: str
    body: bytes


@dataclass
class _Hook:
    webhook: Webhook
    health: WebhookHealth = field(default_factory=WebhookHealth)
    queue: deque[_Delivery] = field(default_factory=deque)
    tries: int = 0  # failed tries of the delivery at the head of the queue
    due: float = 0.0  # monotonic: not before then (backoff)
    sending: bool = False


@dataclass(frozen=True)
class DeliveryPolicy:
    timeout_s: float = 5.0
    max_tries: int = 6
    backoff_base_s: float = 1.0
    backoff_cap_s: float = 60.0
    max_queued: int = 10_000
    workers: int = 2
    # Where deliveries may connect (public addresses unless the plant names more).
    destinations: DestinationPolicy = field(default_factory=DestinationPolicy)


class WebhookDeliveries:
    """Constructing it does no I/O; `start()` starts the workers."""

    def __init__(
        self,
        policy: DeliveryPolicy,
        *,
        client: httpx.Client | None = None,
        monotonic: Callable[[], float] = time.monotonic,
        wall_s: Callable[[], float] = time.time,
    ) -> None:
        self.policy = policy
        self.client = client or guarded_client(policy.destinations, policy.timeout_s)
        self.monotonic, self.wall_s = monotonic, wall_s
        self._hooks: dict[str, _Hook] = {}
        self._queued = 0
        self._seq = itertools.count()
        self._cv = threading.Condition()
        self._threads: list[threading.Thread] = []
        self._stopping = False

    # --- the registry ---------------------------------------------------------------------

    def set_webhooks(self, webhooks: Iterable[Webhook]) -> None:
        """The webhooks registered now: new ones added, removed ones dropped with what they
        had queued, changed ones (URL, kinds, secret) updated in place."""
        wanted = {w.webhook_id: w for w in webhooks}
        with self._cv:
            for webhook_id in list(self._hooks):
                if webhook_id not in wanted:
                    self._queued -= len(self._hooks.pop(webhook_id).queue)
            for webhook_id, webhook in wanted.items():
                hook = self._hooks.get(webhook_id)
                if hook is None:
                    self._hooks[webhook_id] = _Hook(webhook)
                else:
                    hook.webhook = webhook
            QUEUED.set(self._queued)
            self._cv.notify_all()

    def resume(self, webhook_id: str) -> bool:
        """Sends a paused webhook's deliveries again, at once; False if it is unknown."""
        with self._cv:
            hook = self._hooks.get(webhook_id)
            if hook is None:
                return False
            hook.health.resume()
            hook.tries, hook.due = 0, 0.0
            self._cv.notify_all()
            return True

    def health(self) -> dict[str, WebhookHealth]:
        """Each webhook's state and counts (copies)."""
        with self._cv:
            return {k: dataclasses.replace(h.health) for k, h in self._hooks.items()}

    def queued(self, webhook_id: str) -> int:
        with self._cv:
            hook = self._hooks.get(webhook_id)
            return 0 if hook is None else len(hook.queue)

    # --- the pipeline's side: never waits -------------------------------------------------

    def offer(self, alert: dict[str, Any]) -> int:
        """Queues `alert` for every webhook that wants its kind; returns for how many."""
        with self._cv:
            hooks = [h for h in self._hooks.values() if h.webhook.wants(str(alert["kind"]))]
            if not hooks:
                return 0
            body = _json.encode(alert)
            for hook in hooks:
                if self._queued >= self.policy.max_queued:
                    self._drop_oldest()
                hook.queue.append(_Delivery(next(self._seq), uuid.uuid4().hex, body))
                self._queued += 1
            QUEUED.set(self._queued)
            self._cv.notify_all()
            return len(hooks)

    def _drop_oldest(self) -> None:
        heads = [h for h in self._hooks.values() if len(h.queue) > (1 if h.sending else 0)]
        if not heads:
            return
        oldest = min(heads, key=lambda h: h.queue[1 if h.sending else 0].seq)
        # the delivery being sent stays: its worker still holds it
        del oldest.queue[1 if oldest.sending else 0]
        if not oldest.sending:
            oldest.tries, oldest.due = 0, 0.0
        oldest.health.dropped += 1
        self._queued -= 1
        DELIVERIES.labels("dropped").inc()

    # --- the workers ----------------------------------------------------------------------

    def start(self) -> None:
        if self._threads:
            return
        for n in range(self.policy.workers):
            thread = threading.Thread(target=self._work, name=f"webhooks-{n}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def close(self, timeout_s: float = 10.0) -> None:
        """Stops the workers (a send under way ends within its timeout) and the client."""
        with self._cv:
            self._stopping = True
            self._cv.notify_all()
        deadline = self.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - self.monotonic()))
        self._threads = []
        self.client.close()

    def _next(self) -> tuple[_Hook, _Delivery] | None:
        """The due head of some webhook's queue (oldest first), marked as being sent; None
        once stopping. Waits for one."""
        with self._cv:
            while not self._stopping:
                now = self.monotonic()
                ready = [
                    h
                    for h in self._hooks.values()
                    if h.queue and not h.sending and not h.health.paused_reason
                ]
                due = [h for h in ready if h.due <= now]
                if due:
                    hook = min(due, key=lambda h: h.queue[0].seq)
                    hook.sending = True
                    return hook, hook.queue[0]
                wait = min((h.due - now for h in ready), default=None)
                self._cv.wait(timeout=wait)
            return None

    def _work(self) -> None:
        while (taken := self._next()) is not None:
            hook, delivery = taken
            error = self._send(hook.webhook, delivery)
            with self._cv:
                self._sent(hook, delivery, error)

    def _send(self, webhook: Webhook, delivery: _Delivery) -> str:
        """One try; the error, or "" when the receiver answered 2xx."""
        headers = signed_headers(webhook.secret, int(self.wall_s()), delivery.body)
        headers[WEBHOOK_ID_HEADER] = webhook.webhook_id
        headers[DELIVERY_HEADER] = delivery.delivery_id
        try:
            # The answer's status is all a delivery needs: its body is never read (a receiver
            # answering without end would fill the memory), and the try ends within the
            # timeout in all, however slowly the receiver answers.
            with (
                try_within(self.policy.timeout_s),
                self.client.stream(
                    "POST", webhook.url, content=delivery.body, headers=headers
                ) as response,
            ):
                status = response.status_code
        except httpx.TimeoutException:
            return f"no answer within {self.policy.timeout_s:g} s"
        except httpx.HTTPError as exc:
            return f"{type(exc).__name__}: {exc}"[:500]
        except Exception as exc:  # noqa: BLE001 - a worker that died would stop every webhook
            # A URL stored before a stricter check, or one the client cannot send to: the
            # try fails with the reason and the worker goes on with the other webhooks.
            log.warning(
                "webhook delivery could not be sent", webhook=webhook.webhook_id, exc_info=True
            )
            return f"{type(exc).__name__}: {exc}"[:500]
        if 200 <= status < 300:
            return ""
        return f"HTTP {status}"

    def _sent(self, hook: _Hook, delivery: _Delivery, error: str) -> None:
        hook.sending = False
        current = self._hooks.get(hook.webhook.webhook_id)
        if current is not hook or not hook.queue or hook.queue[0] is not delivery:
            self._cv.notify_all()  # removed, or dropped meanwhile
            return
        if not error:
            hook.queue.popleft()
            self._queued -= 1
            QUEUED.set(self._queued)
            hook.tries, hook.due = 0, 0.0
            hook.health.succeeded(int(self.wall_s() * 1000))
            DELIVERIES.labels("delivered").inc()
        else:
            hook.tries += 1
            hook.health.tried_and_failed(error, int(self.wall_s() * 1000))
            DELIVERIES.labels("failed_try").inc()
            if hook.tries >= self.policy.max_tries:
                hook.health.pause(hook.tries)
                log.warning(
                    "webhook paused",
                    webhook=hook.webhook.webhook_id,
                    reason=hook.health.paused_reason,
                )
            else:
                wait = backoff_s(hook.tries, self.policy.backoff_base_s, self.policy.backoff_cap_s)
                hook.due = self.monotonic() + wait
        self._cv.notify_all()
