"""A processors replica follows the webhooks registry without a restart: a webhook
registered gets the next alerts, signed with the secret derived for it; a removed one gets
none; a paused one's reason is reported to the store, and a resume saved by the API makes
the replica send what waited. A registry that cannot be read leaves the deliveries as they
were."""

from __future__ import annotations

import asyncio
import time

import msgspec

from mapservice.core.webhook_registry import RegisteredWebhook, combined_state
from mapservice.core.webhooks import derived_secret, verify
from mapservice.local.embedded import free_port
from mapservice.processors.webhook_delivery import WebhookDeliveries
from mapservice.processors.webhook_registry_sync import WebhookRegistrySync
from mapservice.testing.memory_store import MemoryStore
from tests.processors.test_webhook_delivery import POLICY, Receiver, wait_for

KEY = "signing-key-" + "k" * 32
NOW = 1_795_255_200_000


def alert(kind: str = "stuck", n: int = 1) -> dict:
    return {"event": "new", "found_ms": NOW, "id": f"i{n}", "kind": kind}


def registered(n: int, port: int, kinds: tuple[str, ...] = ()) -> RegisteredWebhook:
    return RegisteredWebhook(
        f"wh-{n:016x}", f"http://127.0.0.1:{port}/hook", kinds, NOW + n, "operator:x"
    )


class Replica:
    def __init__(self) -> None:
        self.store = MemoryStore()
        self.now = NOW
        self.deliveries = WebhookDeliveries(POLICY)
        self.sync = WebhookRegistrySync(
            self.store, self.deliveries, KEY, lambda: self.now, replica="host:1"
        )
        self.deliveries.start()

    def report(self, webhook_id: str):
        reports = [r for r in self.store.webhook_reports() if r.webhook_id == webhook_id]
        return combined_state(reports, self.now, 60_000)


def test_a_registered_webhook_gets_the_next_alerts_signed_and_a_removed_one_none() -> None:
    port = free_port()
    receiver = Receiver(port)
    replica = Replica()
    try:
        assert replica.deliveries.offer(alert()) == 0  # nothing registered yet
        hook = registered(1, port, ("stuck",))
        replica.store.save_webhook(hook, NOW)
        assert replica.sync.sync() == 1
        assert replica.deliveries.offer(alert("near_miss")) == 0  # not a kind it wants
        assert replica.deliveries.offer(alert("stuck")) == 1
        wait_for(lambda: replica.deliveries.queued(hook.webhook_id) == 0)
        ((_, headers, body),) = receiver.requests
        secret = derived_secret(KEY, hook.webhook_id)
        assert verify(secret, headers, body, time.time())
        assert headers["X-Mapservice-Webhook"] == hook.webhook_id
        replica.sync.sync()
        state = replica.report(hook.webhook_id)
        assert (state.state, state.delivered, state.last_result) == ("active", 1, "delivered")
        replica.store.remove_webhook(hook.webhook_id, NOW + 10)
        assert replica.sync.sync() == 0
        assert replica.deliveries.offer(alert("stuck")) == 0
    finally:
        replica.deliveries.close()
        receiver.close()


def test_a_paused_webhook_is_reported_and_resumed_once_the_api_saves_a_resume() -> None:
    port = free_port()
    receiver = Receiver(port, 500)
    replica = Replica()
    try:
        hook = registered(1, port)
        replica.store.save_webhook(hook, NOW)
        replica.sync.sync()
        replica.deliveries.offer(alert())
        wait_for(lambda: replica.deliveries.health()[hook.webhook_id].state == "paused")
        replica.now += 1_000
        replica.sync.sync()
        state = replica.report(hook.webhook_id)
        assert state.state == "paused" and "HTTP 500" in state.paused_reason
        assert state.queued == 1 and state.failed_tries == POLICY.max_tries
        receiver.mode = "ok"
        replica.sync.sync()  # no new resume: still paused
        assert replica.deliveries.health()[hook.webhook_id].state == "paused"
        resumed = msgspec.structs.replace(hook, resumed_ms=NOW + 2_000)
        replica.store.save_webhook(resumed, NOW + 2_000)
        replica.sync.sync()
        wait_for(lambda: replica.deliveries.queued(hook.webhook_id) == 0)
        replica.sync.sync()
        state = replica.report(hook.webhook_id)
        assert (state.state, state.delivered, state.queued) == ("active", 1, 0)
    finally:
        replica.deliveries.close()
        receiver.close()


def test_a_registry_that_cannot_be_read_leaves_the_deliveries_as_they_were(caplog) -> None:
    port = free_port()
    replica = Replica()
    try:
        replica.store.save_webhook(registered(1, port), NOW)
        replica.sync.sync()

        def broken() -> list:
            raise OSError("ClickHouse is away")

        replica.store.webhooks = broken  # type: ignore[method-assign]

        async def run(fn):
            return fn()

        asyncio.run(replica.sync.tick(run))  # logged, not raised
        assert replica.deliveries.offer(alert()) == 1
    finally:
        replica.deliveries.close()


def test_reports_are_written_when_they_change_and_all_at_least_every_heartbeat() -> None:
    port = free_port()
    receiver = Receiver(port)
    replica = Replica()
    written: list[list[str]] = []
    report = replica.store.report_webhooks

    def counted(reports) -> None:
        written.append([r.webhook_id for r in reports])
        report(reports)

    replica.store.report_webhooks = counted  # type: ignore[method-assign]
    try:
        one, two = registered(1, port), registered(2, port, ("near_miss",))
        replica.store.save_webhook(one, NOW)
        replica.store.save_webhook(two, NOW)
        replica.sync.sync()
        assert written == [[one.webhook_id, two.webhook_id]]  # the first: all
        replica.now += 1_000
        replica.sync.sync()
        assert len(written) == 1  # nothing changed, the heartbeat not due
        assert replica.deliveries.offer(alert("stuck")) == 1  # to the first only
        wait_for(lambda: replica.deliveries.health()[one.webhook_id].delivered == 1)
        replica.now += 1_000
        replica.sync.sync()
        assert written[1:] == [[one.webhook_id]]  # only what changed
        replica.now = NOW + replica.sync.heartbeat_ms - 1
        replica.sync.sync()
        assert len(written) == 2
        replica.now += 1
        replica.sync.sync()  # the heartbeat: all again, though unchanged
        assert written[2:] == [[one.webhook_id, two.webhook_id]]
        assert replica.report(one.webhook_id).replicas == 1
    finally:
        replica.deliveries.close()
        receiver.close()
