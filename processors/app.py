"""The processors' faust app: its configuration, the dead letters' agent and the snapshot
timer (composition.py builds the app and wires the parts into it).

At-least-once: offsets are committed (faust: events acknowledged) only after the insert
that holds them succeeded; a crash before that re-delivers the batch, and the history's
natural-identity keys absorb the repeat.
"""

from __future__ import annotations

import ssl
from collections.abc import Awaitable, Callable
from typing import Any

import faust
import structlog
from prometheus_client import Counter

from mapservice.core.ports import RetentionKeeper, SnapshotKeeper
from mapservice.settings import Settings

from .sink import HistorySink, decode_dead_letters

log = structlog.get_logger(__name__)

SNAPSHOT_RUNS = Counter(
    "mapservice_snapshot_runs_total",
    "Snapshot and retention timer runs on this replica (only the group leader runs it)",
)


FAUST_HEARTBEAT_S = 3.0


def faust_broker_url(settings: Settings) -> str:
    return ";".join(f"kafka://{h.strip()}" for h in settings.kafka_bootstrap.split(","))


def faust_app(settings: Settings) -> faust.App:
    """The faust app the processors run in (its agents, timers and services are added by
    the composition, composition.py)."""
    session_s = max(settings.kafka_rebalance_timeout_s, settings.kafka_session_timeout_s)
    return faust.App(
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
        broker_session_timeout=session_s,
        # The faust group carries only the dead letters and the leader's timer: a heartbeat
        # every 3 s (aiokafka's default; a third of the session at most) instead of every
        # second, the largest of `serve`'s timers at a quiet plant, a Kafka request each.
        broker_heartbeat_interval=min(FAUST_HEARTBEAT_S, session_s / 3),
        producer_partitioner=None,
        topic_replication_factor=settings.kafka_replication,
    )


def dead_letter_agent(
    sink: HistorySink, topic: str, batch: int, within: float, now_ms: Callable[[], int]
) -> Callable[[Any], Awaitable[None]]:
    """The dead letters' agent: stored in batches, acknowledged once they are in."""

    async def sink_dead_letters(stream) -> None:
        async for events in stream.noack().noack_take(batch, within=within):
            records = decode_dead_letters((e.value for e in events), now_ms())
            await sink.insert_until_done(
                sink.writer.append_dead_letters, records, {topic: len(records)}
            )
            for e in events:
                e.ack()

    return sink_dead_letters


def snapshot_tick_s(settings: Settings) -> float:
    """The snapshot timer's period in real seconds: a quarter of the snapshot interval (at
    most 30 s of the service's clock), shortened by a simulated clock's rate so snapshots
    and retention keep pace with the time they are built for; MAPSERVICE_SNAPSHOT_TICK_S
    sets it outright."""
    if settings.snapshot_tick_s is not None:
        return settings.snapshot_tick_s
    return max(0.2, min(30.0, settings.snapshot_every_s / 4) / settings.clock_rate)


def snapshot_timer(
    sink: HistorySink,
    snapshots: SnapshotKeeper,
    retention: RetentionKeeper,
    now_ms: Callable[[], int],
    grace_ms: int,
) -> Callable[[], Awaitable[None]]:
    """One tick: repair what late events invalidated (a bounded step), build the snapshots
    due by the service's clock, then the retention step (the anchor snapshot first, so the
    floor crosses the boundary; partitions older than its day dropped), each on the sink's
    thread, the one that talks to the store."""

    async def build_snapshots() -> None:
        SNAPSHOT_RUNS.inc()
        try:
            # Late events first: snapshots they invalidated, a bounded step per tick.
            repaired = await sink.run(snapshots.repair_snapshots)
            if repaired:
                log.info("snapshots repaired after a late event", count=repaired)
            now = now_ms()
            built = await sink.run(snapshots.build_snapshots, now - grace_ms)
            if built:
                log.info("snapshots built", count=built)
            await sink.run(retention.apply_retention, now)
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
            ssl_context.load_cert_chain(
                str(settings.kafka_ssl_cert_file), str(settings.kafka_ssl_key_file)
            )
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
