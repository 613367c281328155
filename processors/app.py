"""The processors: a faust app that sinks the event topics into the ClickHouse history,
keeps the live views, and builds snapshots.

At-least-once: offsets are committed (faust: events acknowledged) only after the insert
that holds them succeeded; a crash before that re-delivers the batch, and the history's
natural-identity keys absorb the repeat.
"""

from __future__ import annotations

import ssl
from collections.abc import Awaitable, Callable

import faust
import structlog
from prometheus_client import Counter

from mapservice.adapters.clock import clock_from_settings
from mapservice.adapters.kafka_batch_source import KafkaBatchSource
from mapservice.settings import Settings

from .history_consumer import COMMIT_FAILURES, HistoryConsumer, HistoryConsumerService
from .sink import HistorySink, decode_dead_letters
from .views import LiveViews

log = structlog.get_logger(__name__)

SNAPSHOT_RUNS = Counter("mapservice_snapshot_runs_total",
                        "Snapshot and retention timer runs on this replica (only the group "
                        "leader runs it)")


def faust_broker_url(settings: Settings) -> str:
    return ";".join(f"kafka://{h.strip()}" for h in settings.kafka_bootstrap.split(","))


def build_app(settings: Settings, sink: HistorySink) -> faust.App:
    app = faust.App(
        "mapservice-processors",
        broker=faust_broker_url(settings),
        broker_credentials=_faust_credentials(settings),
        value_serializer="raw",
        key_serializer="raw",
        web_enabled=False,
        store="memory://",
        datadir=str(settings.data_dir / "faust"),
        topic_partitions=settings.kafka_partitions,
        consumer_auto_offset_reset="earliest",
        broker_commit_interval=1.0,
        # tansu holds a join for the whole rebalance timeout; short keeps start-up quick.
        broker_rebalance_timeout=settings.kafka_rebalance_timeout_s,
        broker_session_timeout=max(settings.kafka_rebalance_timeout_s, 10),
        broker_heartbeat_interval=1.0,
        producer_partitioner=None,
        topic_replication_factor=settings.kafka_replication,
    )
    # Live views: latest map + advertisements, robots, conflicts.
    # The service's clock (the wall clock unless settings simulate one): the timers, the
    # retention step and the views all read it.
    now_ms = clock_from_settings(settings).now_ms
    views = LiveViews.attach(app, settings, sink, now_ms=now_ms)
    batch, within = settings.sink_batch_size, settings.sink_batch_seconds

    # The event topics go to the history in batches below faust's per-record path
    # (history_consumer.py says why); faust runs it, the dead letters, and the timers.
    source = KafkaBatchSource(
        settings, [settings.topic_chunk_events, settings.topic_pose_events,
                   settings.topic_meta_events, settings.topic_annotation_events,
                   settings.topic_command_events],
        group_id=f"{app.conf.id}-history",
        contiguous_topics=[settings.topic_chunk_events, settings.topic_pose_events])
    consumer = HistoryConsumer(source, sink, views, batch, within,
                               min_batch_seconds=settings.sink_batch_min_seconds,
                               views_seconds=settings.sink_views_seconds, now_ms=now_ms)
    source.on_assigned = consumer.on_assigned
    source.on_commit_failed = COMMIT_FAILURES.inc
    sink.consumer = consumer
    app.service(HistoryConsumerService(consumer))

    dl_topic = app.topic(settings.topic_dead_letter, value_type=bytes, key_type=bytes)

    async def sink_dead_letters(stream):
        async for events in stream.noack().noack_take(batch, within=within):
            records = decode_dead_letters((e.value for e in events), now_ms())
            await sink.insert_until_done(sink.store.append_dead_letters, records,
                                         {settings.topic_dead_letter: len(records)})
            for e in events:
                e.ack()

    app.agent(dl_topic, name="history-dead-letters")(sink_dead_letters)

    app.timer(snapshot_tick_s(settings), on_leader=True)(
        snapshot_timer(sink, now_ms, int(settings.snapshot_grace_s * 1000)))
    return app


def snapshot_tick_s(settings: Settings) -> float:
    """The snapshot timer's period in real seconds: a quarter of the snapshot interval (at
    most 30 s of the service's clock), shortened by a simulated clock's rate so snapshots
    and retention keep pace with the time they are built for."""
    return max(0.2, min(30.0, settings.snapshot_every_s / 4) / settings.clock_rate)


def snapshot_timer(sink: HistorySink, now_ms: Callable[[], int], grace_ms: int
                   ) -> Callable[[], Awaitable[None]]:
    """One tick: repair what late events invalidated (a bounded step), build the snapshots
    due by the service's clock, then the retention step (the anchor snapshot first, so the
    floor crosses the boundary; partitions older than its day dropped)."""

    async def build_snapshots() -> None:
        SNAPSHOT_RUNS.inc()
        try:
            # Late events first: snapshots they invalidated, a bounded step per tick.
            repaired = await sink.run(sink.store.repair_snapshots)
            if repaired:
                log.info("snapshots repaired after a late event", count=repaired)
            now = now_ms()
            built = await sink.run(sink.store.build_snapshots, now - grace_ms)
            if built:
                log.info("snapshots built", count=built)
            await sink.run(sink.store.apply_retention, now)
        except Exception as exc:  # the next tick tries again; reads stay correct meanwhile
            log.error("snapshot build or retention failed", error=str(exc))

    return build_snapshots


def _faust_credentials(settings: Settings):
    """The same security settings the confluent-kafka clients use (librdkafka names)."""
    protocol = settings.kafka_security_protocol.upper()
    ssl_context = None
    if protocol in ("SSL", "SASL_SSL"):
        ca_file = str(settings.kafka_ssl_ca_file) if settings.kafka_ssl_ca_file else None
        ssl_context = ssl.create_default_context(cafile=ca_file)
        if settings.kafka_ssl_cert_file and settings.kafka_ssl_key_file:  # mutual TLS
            ssl_context.load_cert_chain(str(settings.kafka_ssl_cert_file),
                                        str(settings.kafka_ssl_key_file))
    if settings.kafka_username and settings.kafka_password:
        return faust.SASLCredentials(
            username=settings.kafka_username,
            password=settings.kafka_password.get_secret_value(),
            mechanism=settings.kafka_sasl_mechanism or "PLAIN",
            ssl_context=ssl_context,
        )
    if ssl_context is not None:
        return faust.SSLCredentials(ssl_context)
    return None
