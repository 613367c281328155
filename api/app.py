"""The FastAPI application: one router per resource, stable operation ids."""

from __future__ import annotations

from collections.abc import Callable

from fastapi import FastAPI

from mapservice import __version__
from mapservice.adapters.clock import SystemClock
from mapservice.live import LiveHub
from mapservice.ports import Clock, EventPublisher, HistoryStore
from mapservice.settings import Settings

from .routers import chunk_contents, chunk_events, health, live, map_state, poses, robots, stats
from .routers import chunk_service, coordinate_service
from .routers import conflicts
from .routers import events, timeline, tracks
from .routers import ui


def create_app(settings: Settings, store: HistoryStore,
               readiness: dict[str, Callable[[], bool]] | None = None,
               clock: Clock | None = None, live_hub: LiveHub | None = None,
               publisher: EventPublisher | None = None) -> FastAPI:
    app = FastAPI(title="mapservice", version=__version__,
                  description="Map and fleet history for factory robots")
    app.state.settings = settings
    app.state.store = store
    app.state.readiness = readiness or {}
    app.state.clock = clock or SystemClock()
    app.state.live = live_hub
    app.state.publisher = publisher  # None: 2019 REST writes answer 503
    for module in (health, map_state, robots, poses, chunk_events, chunk_contents, stats, live):
        app.include_router(module.router)
    for module in (chunk_service, coordinate_service):  # the 2019 REST contract
        app.include_router(module.router)
    app.include_router(conflicts.router)
    for module in (events, timeline, tracks):  # time-travel replay reads
        app.include_router(module.router)
    app.include_router(ui.router)  # the replay UI at / and /controller
    return app
