"""The process entry: runs the processors and/or the API in one asyncio loop around one
ClickHouse connection. Here the connection and the store's roles over it are made
(mapservice/adapters/clickhouse/store.py), the schema awaited, the health checks of what
runs in this process gathered, and the parts started and stopped in order; each part is
composed in its own package (processors/composition.py, api/composition.py), handing its
components the roles they use (mapservice/core/store_roles.py).

With embedded ClickHouse (chdb) only one process may open the data directory, so
`mapservice serve` runs both here; with a ClickHouse server they can run apart
(`mapservice processors`, `mapservice api`) and scale separately. Either way the live
stream goes through Kafka (mapservice/core/live_messages.py): the processors publish each stored
batch, the API's relay reads the live topic.
"""

from __future__ import annotations

import asyncio
import math
import signal
import sys
from collections.abc import Callable
from typing import Any

import structlog
from prometheus_client import Gauge

from mapservice.adapters.clickhouse.admin import ClickHouseAdmin
from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.adapters.clickhouse.migrations import ClickHouseSchema
from mapservice.adapters.clickhouse.store import clickhouse_roles_from_settings
from mapservice.adapters.kafka_topics import ensure_topics
from mapservice.runtime.health import (
    CachedCheck,
    Heartbeat,
    beat_forever,
    kafka_check,
    probe_report,
)
from mapservice.runtime.health_server import serve_health
from mapservice.runtime.heap import freeze_startup_heap
from mapservice.runtime.metrics_gate import metrics_gate
from mapservice.runtime.thread_priority import keep_merges_low
from mapservice.settings import Settings

log = structlog.get_logger(__name__)


CHDB_MEMORY = Gauge(
    "mapservice_chdb_memory_tracked_bytes",
    "Memory ClickHouse's tracker counts inside this process (embedded chDB only)",
)
PYTHON_BLOCKS = Gauge(
    "mapservice_python_allocated_blocks",
    "Memory blocks Python's allocator holds (sys.getallocatedblocks)",
)


def export_process_memory(store: ClickHouseAdmin) -> None:
    """With chDB, ClickHouse lives in this process: its tracked memory and Python's
    allocations, side by side with the resident size, say which of the two a growth is in."""
    CHDB_MEMORY.set_function(lambda: _or_nan(store.tracked_memory_bytes))
    PYTHON_BLOCKS.set_function(sys.getallocatedblocks)


def _or_nan(read: Callable[[], float]) -> float:
    try:
        return float(read())
    except Exception:  # a scrape must not fail because ClickHouse is busy or closing
        return math.nan


async def wait_for_schema(store: ClickHouseSchema, every_s: float = 2.0) -> int:
    """Waits until `mapservice migrate` has brought the schema to this release's version
    (production: migrations run once per release, never from every pod at once)."""
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION

    loop = asyncio.get_running_loop()
    said = -1
    while True:
        version = await loop.run_in_executor(None, store.schema_version)
        if version >= SCHEMA_VERSION:
            if version > SCHEMA_VERSION:
                log.warning(
                    "the schema is newer than this release", schema=version, release=SCHEMA_VERSION
                )
            return version
        if version != said:
            log.warning(
                "waiting for the schema migration: run `mapservice migrate` (the "
                "migrate Job in infra/k8s)",
                schema=version,
                needed=SCHEMA_VERSION,
            )
            said = version
        await asyncio.sleep(every_s)


async def serve(
    settings: Settings, *, processors: bool = True, api: bool = True, health_port: int | None = None
) -> None:
    connection = ClickHouseConnection.from_settings(settings)
    roles = clickhouse_roles_from_settings(settings, connection)
    parts = None
    if processors:
        # Imported only where they run: an API process alone registers (and exports) none
        # of the processors' metrics.
        from mapservice.processors.composition import compose_processors

        parts = compose_processors(settings, roles)
    loop = asyncio.get_running_loop()
    if settings.migrates_on_start:
        # With the processors here, on their store thread: the one that talks to the store.
        version = await (
            parts.store_thread.run(roles.schema.migrate)
            if parts is not None
            else loop.run_in_executor(None, roles.schema.migrate)
        )
    else:
        version = await wait_for_schema(ClickHouseSchema(connection))
    log.info("history schema ready", version=version, dsn=connection.dsn.split("@")[-1])
    if parts is not None:
        await loop.run_in_executor(None, ensure_topics, settings)
        await parts.start()
        log.info("processors started", kafka=settings.kafka_bootstrap)
    # Readiness: a real call to each dependency (cached, bounded by a timeout). Liveness:
    # heartbeats of the loops that do the work (mapservice/runtime/health.py).
    kafka = kafka_check(settings)
    readiness: dict[str, Callable[[], bool]] = {
        "clickhouse": CachedCheck("clickhouse", connection.ping, ttl_s=2.0, timeout_s=2.0)
    }
    merges_low = None
    if connection.dsn.startswith("chdb://"):
        export_process_memory(ClickHouseAdmin(connection))
        merges_low = keep_merges_low(settings)
    advisory: dict[str, Callable[[], bool]] = {}  # reported by /readyz, not required
    loop_beat = Heartbeat(max_age_s=15.0)
    beating = asyncio.ensure_future(beat_forever(loop_beat))
    liveness = {"event_loop": loop_beat.alive}
    # Whether the history is being stored, where that is known.
    history_status: Callable[[], dict[str, Any]] | None = None
    if parts is not None:
        readiness["kafka"] = kafka
        readiness.update(parts.readiness())
        liveness.update(parts.liveness())
        history_status = parts.history_status
    else:
        # The API alone reads the history without Kafka; Kafka carries its REST writes and
        # the live stream, so /readyz reports it without requiring it.
        advisory["kafka"] = kafka
        if api and settings.processors_status_url:
            # The processors in a process of their own (`mapservice up`): whether the history
            # is stored, as their health endpoint says, required as in one process.
            from mapservice.adapters.processors_status import ProcessorsStatus

            processors_apart = ProcessorsStatus(settings.processors_status_url)
            readiness["history_store"] = processors_apart
            history_status = processors_apart.status
    api_parts = None
    try:
        if api:
            from mapservice.api.composition import compose_api

            api_parts = await compose_api(
                settings,
                roles,
                readiness=readiness,
                liveness=liveness,
                advisory=advisory,
                history_status=history_status,
            )
            api_parts.start()
            log.info("api listening", url=f"http://{settings.api_host}:{settings.api_port}")
            freeze_startup_heap()  # everything is built: the app, the processors, their clients
            await api_parts.serve()
        else:
            stop = asyncio.Event()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            if health_port is not None:
                serve_health(
                    settings.api_host,
                    health_port,
                    lambda: probe_report(liveness),
                    lambda: probe_report(readiness),
                    metrics_gate(settings),
                    documents={"/history-status": parts.history_status}
                    if parts is not None
                    else None,
                )
            freeze_startup_heap()
            await stop.wait()
    finally:
        beating.cancel()
        if merges_low is not None:
            merges_low.stop()
        if api_parts is not None:
            await api_parts.stop()
        if parts is not None:
            await parts.stop()
        connection.close()
        log.info("stopped")
