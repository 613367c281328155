"""The FastAPI application: one router per resource, stable operation ids."""

from __future__ import annotations

from collections.abc import Callable

from fastapi import FastAPI

from mapservice import __version__
from mapservice.adapters.clock import SystemClock
from mapservice.live import LiveHub
from mapservice.ports import Clock, HistoryStore
from mapservice.settings import Settings

from .routers import chunk_contents, chunk_events, health, live, map_state, poses, robots, stats


def create_app(settings: Settings, store: HistoryStore,
               readiness: dict[str, Callable[[], bool]] | None = None,
               clock: Clock | None = None, live_hub: LiveHub | None = None) -> FastAPI:
    app = FastAPI(title="mapservice", version=__version__,
                  description="Map and fleet history for factory robots")
    app.state.settings = settings
    app.state.store = store
    app.state.readiness = readiness or {}
    app.state.clock = clock or SystemClock()
    app.state.live = live_hub
    for module in (health, map_state, robots, poses, chunk_events, chunk_contents, stats, live):
        app.include_router(module.router)
    return app
