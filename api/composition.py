"""The API of one process, composed in one place: the live stream's hub and the relay that
feeds it from the live topic, the publisher of the 2019 REST writes, the FastAPI app and
the uvicorn server around it.

The process entry (mapservice/server.py) makes the store's roles over one connection (with
embedded chDB one per process, shared with the processors), hands the API the health checks of what runs beside
it, starts the API, serves it and stops it (`Api`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import uvicorn
from fastapi import FastAPI

from mapservice.adapters.clock import clock_from_settings
from mapservice.adapters.kafka_live_relay import KafkaLiveRelay
from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.adapters.mcap_export import ReplaySources
from mapservice.core.live_messages import LiveText
from mapservice.core.ports import HistoryStore
from mapservice.core.store_roles import StoreRoles
from mapservice.runtime.secrets import with_local_api_secrets, with_local_webhook_key
from mapservice.settings import Settings
from mapservice.sql.apps import analyst_app

from .app import create_app
from .foxglove_service import FoxgloveService
from .http_timeouts import header_deadline_protocol
from .limits import WEBSOCKET_MAX_MESSAGE_BYTES
from .live_hub import LiveHub

Check = Callable[[], bool]


def api_server_config(app: FastAPI, settings: Settings) -> uvicorn.Config:
    """uvicorn for the API. log_config=None: uvicorn's records, its access log included, go
    through the process's logging setup (mapservice.runtime.logs: JSON lines in JSON mode).
    A request's head must arrive within api_header_timeout_s and an idle keep-alive
    connection is closed after api_idle_timeout_s (slowloris; api/http_timeouts.py). A
    WebSocket client's message over WEBSOCKET_MAX_MESSAGE_BYTES is refused (1009) by the
    websockets library as it reads and inflates it (api/limits.py)."""
    return uvicorn.Config(
        app,
        host=settings.api_host,
        port=settings.api_port,
        log_config=None,
        log_level=None,
        access_log=True,
        http=header_deadline_protocol(settings.api_header_timeout_s),
        timeout_keep_alive=settings.api_idle_timeout_s,
        ws_per_message_deflate=settings.api_live_compression,
        ws_max_size=WEBSOCKET_MAX_MESSAGE_BYTES,
    )


@dataclass(frozen=True, eq=False)
class Api:
    """The composed API (`compose_api`) and its lifecycle."""

    app: FastAPI
    hub: LiveHub
    relay: KafkaLiveRelay
    publisher: KafkaPublisher
    server: uvicorn.Server
    foxglove: FoxgloveService | None = None

    def start(self) -> None:
        """The relay starts reading the live topic; until it reads every partition,
        /api/v1/live asks clients to come back (1013)."""
        self.relay.start()

    async def serve(self) -> None:
        """Serves HTTP (and Foxglove clients) until the process is told to stop (uvicorn
        handles the signals)."""
        if self.foxglove is not None:
            await self.foxglove.start()
        await self.server.serve()

    async def stop(self) -> None:
        """The relay, then the REST writes' producer: a request waits for its record's
        delivery, so once uvicorn has served the last one nothing is left to deliver, and a
        producer left open would keep dialling Kafka until the process exits."""
        loop = asyncio.get_running_loop()
        if self.foxglove is not None:
            await self.foxglove.stop()
        await loop.run_in_executor(None, self.relay.stop)
        await loop.run_in_executor(None, self.publisher.close)


async def compose_api(
    settings: Settings,
    store: HistoryStore | StoreRoles,
    *,
    readiness: Mapping[str, Check],
    liveness: Mapping[str, Check],
    advisory: Mapping[str, Check],
    history_status: Callable[[], dict[str, Any]] | None,
) -> Api:
    """Builds the API around the store's roles (the app cuts a whole store into them); nothing is served
    or read until `Api.start`/`serve`.

    `readiness` (required) and `advisory` (reported) are the checks /readyz answers with,
    `liveness` the ones /healthz does; `history_status` says whether the history is being
    stored, where the inserts happen (the processors beside it, or apart)."""
    loop = asyncio.get_running_loop()
    # 2019 REST writes (POST /chunks, /meta) go to Kafka like MQTT writes do.
    publisher = KafkaPublisher(settings, client_id="mapservice-api")
    # Not in the readiness checks: history reads need no Kafka; until the relay reads the
    # live topic, /api/v1/live asks clients to come back (1013).
    hub = LiveHub()

    def to_hub(messages: list[LiveText]) -> None:  # on the relay's thread
        loop.call_soon_threadsafe(hub.publish, messages)

    relay = KafkaLiveRelay(settings, to_hub)
    hub.ready = relay.assigned.is_set
    # Local mode: the API's tokens generated on first start, kept in the data dir
    # (`mapservice up` prints where); production: as set, validated by Settings.
    settings = with_local_webhook_key(with_local_api_secrets(settings))
    clock = clock_from_settings(settings)
    app = create_app(
        settings,
        store,
        readiness,
        clock=clock,
        live_hub=hub,
        publisher=publisher,
        sql_app=await loop.run_in_executor(None, analyst_app, settings),
        liveness=liveness,
        advisory=advisory,
        # /api/v1/status (the UI's banner) reads the inserts' state where they happen.
        history_status=history_status,
    )
    server = uvicorn.Server(api_server_config(app, settings))
    roles = StoreRoles.of(store)
    foxglove = (
        FoxgloveService(settings, ReplaySources.of(roles), hub, clock.now_ms)
        if settings.foxglove_enabled
        else None
    )
    return Api(app, hub, relay, publisher, server, foxglove)
