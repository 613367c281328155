"""The processors of one process, wired in one place: each part built once and handed what
it needs at construction, nothing pointing back.

    store thread ─┬─> history sink ──> history consumer <── Kafka batch source
                  └─> live views ────┘
                        └─> incident alerts ──> webhook deliveries (threads of their own)
    faust app: runs the consumer, the dead letters' agent, the snapshot timer, presence,
               the webhook registry's sync

The process entry (mapservice/server.py) makes the store (with embedded chDB one per
process, shared with the API), composes the processors around it, starts and stops them,
and asks `Processors` for their health checks.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import faust

from mapservice.adapters.clock import clock_from_settings
from mapservice.adapters.kafka_batch_source import KafkaBatchSource
from mapservice.adapters.kafka_live_publisher import KafkaLivePublisher
from mapservice.core.ports import HistoryStore
from mapservice.core.store_roles import StoreRoles
from mapservice.runtime.secrets import with_local_webhook_key
from mapservice.settings import Settings

from .advertiser import MqttAdvertiser
from .app import dead_letter_agent, faust_app, snapshot_tick_s, snapshot_timer
from .history_consumer import COMMIT_FAILURES, HistoryConsumer, HistoryConsumerService
from .sink import HistorySink
from .store_thread import StoreThread
from .views import LiveViews
from .webhook_delivery import WebhookDeliveries
from .webhook_registry_sync import WebhookRegistrySync, delivery_policy

Check = Callable[[], bool]


@dataclass(frozen=True, eq=False)
class Processors:
    """The composed processors (`compose_processors`): the parts, their lifecycle and the
    checks that say whether they work."""

    app: faust.App
    store_thread: StoreThread
    sink: HistorySink
    views: LiveViews
    consumer: HistoryConsumer
    live: KafkaLivePublisher
    webhooks: WebhookDeliveries | None = None  # None: no signing key, no webhooks

    def running(self) -> bool:
        return not self.app.should_stop

    def readiness(self) -> dict[str, Check]:
        return {
            "processors": self.running,
            # Ready once the consumer group took this replica in: with partitions it stores
            # events, without (more replicas than partitions) it is a healthy standby that
            # takes partitions over when another replica leaves.
            "history_consumer": lambda: self.consumer.joined,
            # ClickHouse answers `SELECT 1` with a full disk: whether inserts succeed is its
            # own check, and it says why not (mapservice/runtime/insert_health.py).
            "history_store": self.sink.health,
        }

    def liveness(self) -> dict[str, Check]:
        return {"processors": self.running, "history_consumer": self.consumer.heartbeat.alive}

    def history_status(self) -> dict[str, Any]:
        """Whether the history is being stored, as /api/v1/status and the UI's banner say."""
        return self.sink.health.status()

    async def start(self) -> None:
        if self.webhooks is not None:
            self.webhooks.start()
        await self.app.start()

    async def stop(self) -> None:
        """The app (the consumer settles and closes its source), then the live stream's
        producer and the webhooks' workers (a send under way ends within its timeout),
        then the store thread once what was handed to it is done."""
        await self.app.stop()
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, self.live.close)
        if self.webhooks is not None:
            await loop.run_in_executor(None, self.webhooks.close)
        self.store_thread.close()


def compose_processors(settings: Settings, store: HistoryStore | StoreRoles) -> Processors:
    """Builds the processors around the store's roles (a whole store is cut into them
    here): each part is handed the roles it uses, none the whole store. Nothing connects until `Processors.start`."""
    roles = StoreRoles.of(store)
    # Local mode: the webhooks' signing key generated once in the data dir, as the API's.
    settings = with_local_webhook_key(settings)
    app = faust_app(settings)
    # The service's clock (the wall clock unless settings simulate one): the timers, the
    # retention step and the views all read it.
    now_ms = clock_from_settings(settings).now_ms
    store_thread = StoreThread()
    live = KafkaLivePublisher(settings)
    sink = HistorySink(roles.writer, live, thread=store_thread, retention_ms=settings.retention_ms)

    # The incident alerts' webhooks: delivered on threads of their own, the registry
    # re-read (and the deliveries reported) by a timer on every replica.
    signing_key = settings.webhook_signing_key.get_secret_value()
    webhooks = WebhookDeliveries(delivery_policy(settings)) if signing_key else None
    if webhooks is not None:
        registry_sync = WebhookRegistrySync(roles.webhooks, webhooks, signing_key, now_ms)

        async def sync_webhooks() -> None:
            await registry_sync.tick(store_thread.run)

        app.timer(settings.webhook_registry_poll_s)(sync_webhooks)

    # Live views: latest map + advertisements, robots, conflicts; rebuilt by the history
    # consumer on every partition assignment.
    advertiser = MqttAdvertiser(settings)
    views = LiveViews(
        settings,
        history=roles.history,
        annotations=roles.annotations,
        conflicts=roles.conflicts,
        incidents=roles.incidents,
        commands=roles.commands,
        vda=roles.vda,
        writer=roles.writer,
        advertiser=advertiser,
        store_thread=store_thread,
        now_ms=now_ms,
        webhooks=webhooks,
        live=live,
    )

    async def stop_views(sender: object, *args: object, **kwargs: object) -> None:
        await asyncio.get_running_loop().run_in_executor(None, views.close)
        advertiser.stop()

    # faust's receiver hint (a union of callables) matches no async function for mypy.
    app.on_before_shutdown.connect(stop_views, weak=False)  # type: ignore[arg-type]

    async def presence() -> None:
        await views.tick()

    app.timer(1.0)(presence)

    # The event topics go to the history in batches below faust's per-record path
    # (history_consumer.py says why); faust runs it, the dead letters, and the timers.
    batch, within = settings.sink_batch_size, settings.sink_batch_seconds
    source = KafkaBatchSource(
        settings,
        [
            settings.topic_chunk_events,
            settings.topic_pose_events,
            settings.topic_meta_events,
            settings.topic_annotation_events,
            settings.topic_command_events,
        ],
        group_id=f"{app.conf.id}-history",
        contiguous_topics=[settings.topic_chunk_events, settings.topic_pose_events],
    )
    consumer = HistoryConsumer(
        source,
        sink,
        views,
        batch,
        within,
        min_batch_seconds=settings.sink_batch_min_seconds,
        quiet_batch_seconds=settings.sink_quiet_batch_seconds,
        views_seconds=settings.sink_views_seconds,
        now_ms=now_ms,
    )
    source.on_assigned = consumer.on_assigned
    source.on_commit_failed = COMMIT_FAILURES.inc
    # faust's hint names a Service class; an instance is run as it is.
    app.service(HistoryConsumerService(consumer))  # type: ignore[arg-type]

    dl_topic = app.topic(settings.topic_dead_letter, value_type=bytes, key_type=bytes)
    app.agent(dl_topic, name="history-dead-letters")(
        dead_letter_agent(sink, settings.topic_dead_letter, batch, within, now_ms)
    )

    app.timer(snapshot_tick_s(settings), on_leader=True)(
        snapshot_timer(
            sink, roles.snapshots, roles.retention, now_ms, int(settings.snapshot_grace_s * 1000)
        )
    )
    return Processors(app, store_thread, sink, views, consumer, live, webhooks)
