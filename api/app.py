"""The FastAPI application: one router per resource, stable operation ids."""

from __future__ import annotations

from collections.abc import Callable

from fastapi import FastAPI

from mapservice import __version__
from mapservice.ports import HistoryStore
from mapservice.settings import Settings

from .routers import chunk_contents, chunk_events, health, poses, stats


def create_app(settings: Settings, store: HistoryStore,
               readiness: dict[str, Callable[[], bool]] | None = None) -> FastAPI:
    app = FastAPI(title="mapservice", version=__version__,
                  description="Map and fleet history for factory robots")
    app.state.settings = settings
    app.state.store = store
    app.state.readiness = readiness or {}
    for module in (health, poses, chunk_events, chunk_contents, stats):
        app.include_router(module.router)
    return app
