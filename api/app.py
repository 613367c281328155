"""The FastAPI application: one router per resource, stable operation ids."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi_offline import FastAPIOffline
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette_exporter import PrometheusMiddleware

from mapservice import __version__
from mapservice.adapters.clock import SystemClock
from mapservice.api.live_hub import LiveHub
from mapservice.core.ports import Clock, EventPublisher, HistoryStore
from mapservice.core.store_roles import StoreRoles
from mapservice.settings import Settings

from .access import check_routes, document_scopes
from .access_guard import AccessGuard
from .admission import AdmissionControl, default_pool_of
from .context import ApiContext
from .credentials import Credentials
from .limits import BodyLimit, HostCheck, allowed_hosts, validation_error
from .routers import (
    annotations as annotation_routes,
)
from .routers import (
    caller,
    changes,
    chunk_contents,
    chunk_events,
    chunk_service,
    client_config,
    commands,
    conflicts,
    coordinate_service,
    costmap_filters,
    events,
    exports,
    health,
    heatmaps,
    incidents,
    live,
    map_state,
    poses,
    robots,
    stats,
    status,
    timeline,
    tracks,
    ui,
    vda5050,
    webhooks,
    zone_violations,
)

# Resources of the API, then the 2019 contract, then the pages (ui last: it owns `/`).
ROUTERS = (
    health,
    map_state,
    vda5050,
    robots,
    tracks,
    poses,
    chunk_events,
    chunk_contents,
    events,
    timeline,
    conflicts,
    changes,
    annotation_routes,
    commands,
    costmap_filters,
    incidents,
    webhooks,
    heatmaps,
    zone_violations,
    exports,
    stats,
    status,
    live,
    caller,
    client_config,
    chunk_service,
    coordinate_service,
    ui,
)


def create_app(
    settings: Settings,
    store: HistoryStore | StoreRoles | None,
    readiness: Mapping[str, Callable[[], bool]] | None = None,
    clock: Clock | None = None,
    live_hub: LiveHub | None = None,
    publisher: EventPublisher | None = None,
    sql_app: ASGIApp | None = None,
    pool_of: Callable[[str], str | None] = default_pool_of,
    *,
    liveness: Mapping[str, Callable[[], bool]] | None = None,
    advisory: Mapping[str, Callable[[], bool]] | None = None,
    history_status: Callable[[], dict[str, Any]] | None = None,
) -> FastAPI:
    """The app over the store's roles (a whole store is cut into them here): the routes are handed one role each
    through api/deps.py, none the whole store. `store` None builds the routes only (the
    OpenAPI document). `pool_of` names the admission pool of a path (api/admission.py);
    `readiness` and `advisory` are the checks /readyz answers with, `liveness` those of
    /healthz; `history_status` says whether this process stores the history."""
    # /docs and /redoc with Swagger UI and ReDoc served from the installed package, not a
    # CDN: a plant network often has no internet.
    app = FastAPIOffline(
        title="mapservice",
        version=__version__,
        description="Map and fleet history for factory robots",
    )
    # The tokens as the settings hold them: local mode's generated ones are filled in by
    # the process before (mapservice/runtime/secrets.py); an empty one opens nothing.
    credentials = Credentials(settings)
    # The app's one state: everything the routes and middlewares are given (api/context.py).
    app.state.context = ApiContext(
        settings=settings,
        clock=clock or SystemClock(),
        roles=None if store is None else StoreRoles.of(store),
        access=credentials,
        export_executor=ThreadPoolExecutor(
            settings.api_export_workers, thread_name_prefix="exports"
        ),
        publisher=publisher,
        live=live_hub,
        readiness=dict(readiness or {}),
        liveness=dict(liveness or {}),
        advisory=dict(advisory or {}),
        history_status=history_status,
    )
    for module in ROUTERS:
        app.include_router(module.router)
    check_routes(app)
    document_scopes(app)
    # Request rate, errors and duration per route template (mapservice_api_requests_total,
    # mapservice_api_request_duration_seconds); probes and scrapes are not counted, and
    # paths that match no route share one label instead of one series per URL.
    app.add_middleware(
        PrometheusMiddleware,
        app_name="mapservice-api",
        prefix="mapservice_api",
        group_paths=True,
        filter_unhandled_paths=True,
        skip_paths=["/metrics", "/healthz", "/readyz"],
        buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
    )
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_middleware(
        BodyLimit,
        max_bytes=settings.api_max_body_bytes,
        exempt=(SQL_PATH,),
        timeout_s=settings.api_body_timeout_s,
    )
    if sql_app is not None:
        # Analysts' read-only SQL, as a ClickHouse server speaks it over HTTP (mapservice/sql):
        # clickhouse-connect, Grafana's ClickHouse data source and curl point at it unchanged.
        # Inside the rate limits and the pools: analysts are callers like any other.
        app.add_middleware(PathPrefix, prefix=SQL_PATH, target=sql_app)
    # Pools and per-caller caps (api/admission.py): a costly request waits or is refused
    # before it takes a thread; inside the guard, which names the caller.
    app.add_middleware(AdmissionControl, settings=settings, pool_of=pool_of)
    # Outside the body limit: a caller over its rate is refused before its body is read.
    app.add_middleware(
        AccessGuard,
        credentials=credentials,
        sql_path=SQL_PATH,
        sql_identify=getattr(getattr(sql_app, "state", None), "identify", None),
    )
    if settings.api_allowed_origins:
        # Pages of these origins may call the API from a browser (preflights answered here,
        # before any credential is asked for); none by default: same origin only. Tokens
        # travel in the Authorization header, never in cookies, so no credentials mode.
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.api_allowed_origins,
            allow_methods=["GET", "POST", "PUT", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
            expose_headers=[
                "Retry-After",
                "X-Map-At-Ms",
                "X-Chunk-Width",
                "X-Chunk-Height",
                heatmaps.SUMMARY_HEADER,
            ],
            max_age=600,
        )
    # Outermost: a request under another site's host name (DNS rebinding) reaches nothing,
    # not even the rate limiter; one check for every route, the WebSocket and /clickhouse.
    app.add_middleware(HostCheck, allowed=allowed_hosts(settings))
    return app


SQL_PATH = "/clickhouse"


class PathPrefix:
    """Sends `prefix` and everything under it to `target`, the bare prefix included. Not a
    Starlette Mount: a Mount answers the bare prefix with a redirect, and a client that
    streams its body (clickhouse-connect's inserts) re-sends it empty after a redirect."""

    def __init__(self, app: ASGIApp, prefix: str, target: ASGIApp):
        self.app, self.prefix, self.target = app, prefix, target

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if scope["type"] == "http" and (path == self.prefix or path.startswith(self.prefix + "/")):
            rest = path[len(self.prefix) :] or "/"
            scope = dict(
                scope,
                path=rest,
                raw_path=rest.encode(),
                root_path=scope.get("root_path", "") + self.prefix,
            )
            await self.target(scope, receive, send)
            return
        await self.app(scope, receive, send)
