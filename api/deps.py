"""What routers share: the parts of the app's context (api/context.py) as dependencies,
one role of the store each, and time-parameter parsing.

A route declares what it uses with the aliases below (`HistoryDep`, `SettingsDep`...): each
resolves to one part of the context, so no route is handed the store as a whole."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Query
from pydantic import BaseModel, Field
from starlette.requests import HTTPConnection

from mapservice.core.ports import (
    AnnotationReader,
    ChangeFeed,
    Clock,
    CommandReader,
    ConflictReader,
    LegacyQueries,
    StoreAdmin,
    TableExports,
    TimeTravelReader,
    VdaReader,
)
from mapservice.core.store_roles import StoreRoles
from mapservice.core.wire2019 import parse_query_instant
from mapservice.settings import Settings

from .annotation_state import RecentEdits
from .content_cache import ContentCache
from .context import ApiContext, Check, context_of
from .live_hub import LiveHub


async def api_context(connection: HTTPConnection) -> ApiContext:
    """The context `create_app` built (HTTP requests and WebSockets alike). These
    dependencies are async because they only read it: a sync one would take a thread of
    the pool the reads use (the probes must answer while every one of those is busy)."""
    return context_of(connection.app)


Context = Annotated[ApiContext, Depends(api_context)]


async def get_settings(context: Context) -> Settings:
    return context.settings


async def get_clock(context: Context) -> Clock:
    return context.clock


async def _roles(context: Context) -> StoreRoles:
    if context.roles is None:
        raise HTTPException(503, "this API app was built without a history store")
    return context.roles


RolesDep = Annotated[StoreRoles, Depends(_roles)]


async def history_reader(roles: RolesDep) -> TimeTravelReader:
    return roles.history


async def conflict_reader(roles: RolesDep) -> ConflictReader:
    return roles.conflicts


async def annotation_reader(roles: RolesDep) -> AnnotationReader:
    return roles.annotations


async def command_reader(roles: RolesDep) -> CommandReader:
    return roles.commands


async def vda_reader(roles: RolesDep) -> VdaReader:
    return roles.vda


async def change_feed(roles: RolesDep) -> ChangeFeed:
    return roles.changes


async def legacy_queries(roles: RolesDep) -> LegacyQueries:
    return roles.legacy


async def store_admin(roles: RolesDep) -> StoreAdmin:
    return roles.admin


async def table_exports(roles: RolesDep) -> TableExports | None:
    """None for a store without them (only ClickHouse has them): the route says 501."""
    return roles.exports


async def export_executor(context: Context) -> ThreadPoolExecutor:
    return context.export_executor


async def live_hub(context: Context) -> LiveHub | None:
    return context.live


async def readiness_checks(context: Context) -> Mapping[str, Check]:
    return context.readiness


async def liveness_checks(context: Context) -> Mapping[str, Check]:
    return context.liveness


async def advisory_checks(context: Context) -> Mapping[str, Check]:
    return context.advisory


async def content_cache(context: Context) -> ContentCache:
    return context.content_cache


async def recent_edits(context: Context) -> RecentEdits:
    return context.recent_edits


async def history_status(context: Context) -> Callable[[], dict[str, Any]] | None:
    """The inserts' state where the processors run in this process (`mapservice serve`)."""
    return context.history_status


SettingsDep = Annotated[Settings, Depends(get_settings)]
ClockDep = Annotated[Clock, Depends(get_clock)]
HistoryDep = Annotated[TimeTravelReader, Depends(history_reader)]
ConflictsDep = Annotated[ConflictReader, Depends(conflict_reader)]
AnnotationsDep = Annotated[AnnotationReader, Depends(annotation_reader)]
CommandsDep = Annotated[CommandReader, Depends(command_reader)]
VdaDep = Annotated[VdaReader, Depends(vda_reader)]
ChangesDep = Annotated[ChangeFeed, Depends(change_feed)]
LegacyDep = Annotated[LegacyQueries, Depends(legacy_queries)]
AdminDep = Annotated[StoreAdmin, Depends(store_admin)]
ExportsDep = Annotated[TableExports | None, Depends(table_exports)]
ExportPoolDep = Annotated[ThreadPoolExecutor, Depends(export_executor)]
RecentEditsDep = Annotated[RecentEdits, Depends(recent_edits)]
ContentCacheDep = Annotated[ContentCache, Depends(content_cache)]
LiveHubDep = Annotated[LiveHub | None, Depends(live_hub)]
ReadinessDep = Annotated[Mapping[str, Check], Depends(readiness_checks)]
LivenessDep = Annotated[Mapping[str, Check], Depends(liveness_checks)]
AdvisoryDep = Annotated[Mapping[str, Check], Depends(advisory_checks)]
HistoryStatusSource = Annotated[Callable[[], dict[str, Any]] | None, Depends(history_status)]


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
