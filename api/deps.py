"""What routers share: the parts of the app's context (api/context.py) as dependencies,
one role of the store each, and time-parameter parsing.

A route declares what it uses with the aliases below (`HistoryDep`, `SettingsDep`...): each
resolves to one part of the context, so no route is handed the store as a whole."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated, Any, TypeVar

from fastapi import Depends, HTTPException, Query
from pydantic import BaseModel, Field
from starlette.requests import HTTPConnection

from mapservice.core.ports import (
    AnnotationReader,
    ChangeFeed,
    Clock,
    CommandReader,
    ConflictReader,
    EventPublisher,
    HeatmapReader,
    IncidentReader,
    LegacyQueries,
    StoreAdmin,
    TableExports,
    TimeTravelReader,
    VdaReader,
    WebhookRegistry,
)
from mapservice.core.store_roles import StoreRoles
from mapservice.core.wire2019 import parse_query_instant
from mapservice.settings import Settings

from .access import ADMIN, OPERATE, WRITE
from .annotation_state import RecentEdits
from .content_cache import ContentCache
from .context import ApiContext, Check, context_of
from .credentials import Caller
from .live_hub import LiveHub
from .posted_meta import PostedMeta

T = TypeVar("T")


async def api_context(connection: HTTPConnection) -> ApiContext:
    """The context `create_app` built (HTTP requests and WebSockets alike). These
    dependencies are async because they only read it: a sync one would take a thread of
    the pool the reads use (the probes must answer while every one of those is busy)."""
    return context_of(connection.app)


Context = Annotated[ApiContext, Depends(api_context)]


def _part(pick: Callable[[ApiContext], T]) -> Callable[[ApiContext], Awaitable[T]]:
    """A dependency that resolves to one part of the context."""

    async def part(context: Context) -> T:
        return pick(context)

    return part


async def _roles(context: Context) -> StoreRoles:
    if context.roles is None:
        raise HTTPException(503, "this API app was built without a history store")
    return context.roles


RolesDep = Annotated[StoreRoles, Depends(_roles)]


def _role(pick: Callable[[StoreRoles], T]) -> Callable[[StoreRoles], Awaitable[T]]:
    """A dependency that resolves to one role of the store (a 503 without a store)."""

    async def role(roles: RolesDep) -> T:
        return pick(roles)

    return role


async def _publisher(context: Context) -> EventPublisher:
    """The app's publisher, or a 503 saying how to configure one."""
    if context.publisher is None:
        raise HTTPException(
            503,
            "this API instance has no event publisher (Kafka) configured, "
            "so it cannot accept writes; run it with MAPSERVICE_KAFKA_BOOTSTRAP "
            "set (`mapservice api` / `mapservice serve`) or write via MQTT",
        )
    return context.publisher


SettingsDep = Annotated[Settings, Depends(_part(lambda c: c.settings))]
ClockDep = Annotated[Clock, Depends(_part(lambda c: c.clock))]
PublisherDep = Annotated[EventPublisher, Depends(_publisher)]
HistoryDep = Annotated[TimeTravelReader, Depends(_role(lambda r: r.history))]
ConflictsDep = Annotated[ConflictReader, Depends(_role(lambda r: r.conflicts))]
AnnotationsDep = Annotated[AnnotationReader, Depends(_role(lambda r: r.annotations))]
IncidentsDep = Annotated[IncidentReader, Depends(_role(lambda r: r.incidents))]
HeatmapsDep = Annotated[HeatmapReader, Depends(_role(lambda r: r.heatmaps))]
CommandsDep = Annotated[CommandReader, Depends(_role(lambda r: r.commands))]
VdaDep = Annotated[VdaReader, Depends(_role(lambda r: r.vda))]
WebhooksDep = Annotated[WebhookRegistry, Depends(_role(lambda r: r.webhooks))]
ChangesDep = Annotated[ChangeFeed, Depends(_role(lambda r: r.changes))]
LegacyDep = Annotated[LegacyQueries, Depends(_role(lambda r: r.legacy))]
AdminDep = Annotated[StoreAdmin, Depends(_role(lambda r: r.admin))]
# None for a store without them (only ClickHouse has them): the route says 501.
ExportsDep = Annotated[TableExports | None, Depends(_role(lambda r: r.exports))]
ExportPoolDep = Annotated[ThreadPoolExecutor, Depends(_part(lambda c: c.export_executor))]
RecentEditsDep = Annotated[RecentEdits, Depends(_part(lambda c: c.recent_edits))]
PostedMetaDep = Annotated[PostedMeta, Depends(_part(lambda c: c.posted_meta))]
ContentCacheDep = Annotated[ContentCache, Depends(_part(lambda c: c.content_cache))]
LiveHubDep = Annotated[LiveHub | None, Depends(_part(lambda c: c.live))]
ReadinessDep = Annotated[Mapping[str, Check], Depends(_part(lambda c: c.readiness))]
LivenessDep = Annotated[Mapping[str, Check], Depends(_part(lambda c: c.liveness))]
AdvisoryDep = Annotated[Mapping[str, Check], Depends(_part(lambda c: c.advisory))]
# The inserts' state where the processors run in this process (`mapservice serve`).
HistoryStatusSource = Annotated[
    Callable[[], dict[str, Any]] | None, Depends(_part(lambda c: c.history_status))
]
# Who called, once the route's scope admitted them.
WriterCaller = Annotated[Caller, Depends(WRITE)]
OperatorCaller = Annotated[Caller, Depends(OPERATE)]
AdminCaller = Annotated[Caller, Depends(ADMIN)]


def parse_time_param(name: str, value: str) -> int:
    """ISO 8601 (UTC when no zone is given) or epoch milliseconds, 1970 to 2262."""
    ms = parse_query_instant(value)
    if ms is None:
        raise HTTPException(
            400,
            f"query parameter {name!r}: {value!r} is neither ISO 8601 "
            "(e.g. 2026-11-21T10:00:00Z) nor epoch milliseconds between 1970 and 2262",
        )
    return ms


def parse_window(from_: str, to: str, max_span_ms: int) -> tuple[int, int]:
    f, t = parse_time_param("from", from_), parse_time_param("to", to)
    if f > t:
        raise HTTPException(400, f"'from' ({from_}) is after 'to' ({to}); swap them")
    if t - f > max_span_ms:
        raise HTTPException(
            400,
            f"window of {(t - f) / 3_600_000:.1f} h is longer than the "
            f"{max_span_ms / 3_600_000:.0f} h allowed; split it",
        )
    return f, t


def parse_instant(value: str, settings: Settings, now_ms: int) -> int:
    """An instant within the retention and not in the future, else a 400 that says why."""
    at = parse_time_param("at", value)
    if at > now_ms + 1000:
        raise HTTPException(400, f"'at' ({value}) is in the future; the latest instant is now")
    if at < now_ms - settings.retention_ms:
        raise HTTPException(
            400, f"'at' ({value}) is older than the {settings.retention_days}-day retention"
        )
    return at


def at_instant(
    settings: SettingsDep,
    clock: ClockDep,
    at: str | None = Query(None, description="Instant (ISO 8601 or epoch ms); default now"),
) -> int:
    """The `at` query parameter as epoch ms, checked against the retention."""
    now = clock.now_ms()
    return parse_instant(at, settings, now) if at is not None else now


AtDep = Annotated[int, Depends(at_instant)]


def window_in_retention(
    from_: str, to: str, max_span_ms: int, settings: Settings, now_ms: int
) -> tuple[int, int]:
    """parse_window, and a 400 when the window starts before the retention (a minute of
    slack: a client's "now - 7 days" is a little older when it arrives)."""
    f, t = parse_window(from_, to, max_span_ms)
    if f < now_ms - settings.retention_ms - 60_000:
        raise HTTPException(
            400,
            f"'from' ({from_}) is older than the {settings.retention_days}-day retention; "
            "nothing is kept before now minus the retention",
        )
    return f, t


class TimeWindow(BaseModel):
    """The `from` and `to` query parameters of a route that reads a time window, as sent:
    the route parses them (`parse`, `in_retention`) with its own longest span, after any
    check of its own that comes first, so each bad value is the 400 it always was."""

    from_: str = Field(alias="from", description="Start (inclusive), ISO 8601 or epoch ms")
    to: str = Field(description="End (exclusive), ISO 8601 or epoch ms")

    def parse(self, max_span_ms: int) -> tuple[int, int]:
        """Epoch ms (from, to): a 400 for a bad instant, a reversed window or a longer span."""
        return parse_window(self.from_, self.to, max_span_ms)

    def in_retention(self, max_span_ms: int, settings: Settings, now_ms: int) -> tuple[int, int]:
        """`parse`, and a 400 when the window starts before the retention."""
        return window_in_retention(self.from_, self.to, max_span_ms, settings, now_ms)


# A query-parameter model: `from` and `to` stand where the route declares it, first, as
# separate parameters in the OpenAPI document (and so in the UI's generated types).
WindowQuery = Annotated[TimeWindow, Query()]


def check_step(step_ms: int, name: str = "step_ms", every: str = "every pose") -> int:
    """A downsampling step: 0 (`every` row) or a positive number of milliseconds; a
    negative one is a 400 naming the parameter `name`, as every bad value's meaning is."""
    if step_ms < 0:
        raise HTTPException(
            400,
            f"{name} ({step_ms}) is negative; use 0 for {every} or a positive step in milliseconds",
        )
    return step_ms
