"""Clock adapters: the wall clock, a simulated one (a start instant and a rate, from
settings), and a settable one for tests.

Every component that asks "what time is it" for the history's sake (the gateway's
timestamp checks, the snapshot and repair timers, the retention step, the API's "now")
takes its clock from `clock_from_settings`, so a test that runs the service on a
simulated clock runs the code production runs.
"""

from __future__ import annotations

import datetime as dt
import time

from mapservice.settings import Settings


class SystemClock:
    def now_ms(self) -> int:
        return time.time_ns() // 1_000_000


class SimulatedClock:
    """Reads `start_ms` at the real instant `origin_ms` and runs `rate` times as fast."""

    def __init__(self, start_ms: int, rate: float = 1.0, origin_ms: int | None = None) -> None:
        if rate <= 0:
            raise ValueError("a simulated clock's rate must be positive")
        self.start_ms, self.rate = start_ms, rate
        self.origin_ms = time.time_ns() // 1_000_000 if origin_ms is None else origin_ms

    def now_ms(self) -> int:
        return self.start_ms + int((time.time_ns() // 1_000_000 - self.origin_ms) * self.rate)


class ManualClock:
    def __init__(self, now_ms: int) -> None:
        self._now = now_ms

    def now_ms(self) -> int:
        return self._now

    def advance(self, ms: int) -> None:
        self._now += ms


def parse_instant_ms(text: str, name: str) -> int:
    """Epoch milliseconds, or an ISO 8601 instant (UTC unless it names a zone)."""
    text = text.strip()
    if text.lstrip("-").isdigit():
        return int(text)
    try:
        parsed = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"{name}={text!r} is neither epoch milliseconds nor an ISO 8601 instant "
            "(e.g. 2026-01-01T00:00:00Z)"
        ) from None
    if parsed.tzinfo is None:
        parsed = parsed.replace(tzinfo=dt.UTC)
    return int(parsed.timestamp() * 1000)


def clock_from_settings(settings: Settings) -> SystemClock | SimulatedClock:
    """The wall clock, unless MAPSERVICE_CLOCK_START (or a rate other than 1) asks for a
    simulated one."""
    if not settings.clock_start and settings.clock_rate == 1.0:
        return SystemClock()
    start = (
        parse_instant_ms(settings.clock_start, "MAPSERVICE_CLOCK_START")
        if settings.clock_start
        else time.time_ns() // 1_000_000
    )
    origin = (
        parse_instant_ms(settings.clock_origin, "MAPSERVICE_CLOCK_ORIGIN")
        if settings.clock_origin
        else None
    )
    return SimulatedClock(start, settings.clock_rate, origin)
