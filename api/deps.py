"""What routers share: the store, the settings, and time-parameter parsing."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Query, Request
from pydantic import BaseModel, Field

from mapservice.core.ports import Clock, HistoryStore
from mapservice.core.wire2019 import parse_query_instant
from mapservice.settings import Settings


def get_store(request: Request) -> HistoryStore:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_clock(request: Request) -> Clock:
    return request.app.state.clock


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
    at: str | None = Query(None, description="Instant (ISO 8601 or epoch ms); default now"),
    settings: Settings = Depends(get_settings),
    clock: Clock = Depends(get_clock),
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
