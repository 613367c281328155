"""Health that tells the truth: liveness from heartbeats of the loops that do the work,
readiness from real calls to each dependency, each with a short timeout.

- `Heartbeat`: a loop beats on every turn; it is alive while its last beat is recent.
- `CachedCheck`: a dependency call (a `SELECT 1`, a Kafka metadata request) run at most
  every `ttl_s` in a thread of its own; a call slower than `timeout_s` counts as down, and
  a probe never waits longer than that, however the dependency hangs. Once it has an
  answer, a probe gets the last one at once while a refresh runs.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Mapping
from functools import partial
from typing import TYPE_CHECKING, Any

import structlog

if TYPE_CHECKING:
    from confluent_kafka.admin import AdminClient

    from mapservice.settings import Settings

log = structlog.get_logger(__name__)

REFRESH_WAIT_S = 0.1  # how long a probe with an earlier answer waits for a refresh


class Heartbeat:
    def __init__(self, max_age_s: float, clock: Callable[[], float] = time.monotonic):
        self.max_age_s, self.clock = max_age_s, clock
        self.last: float | None = None

    def beat(self) -> None:
        self.last = self.clock()

    def alive(self) -> bool:
        """True before the first beat (still starting) and while beats are recent."""
        return self.last is None or self.clock() - self.last <= self.max_age_s

    def age_s(self) -> float | None:
        return None if self.last is None else round(self.clock() - self.last, 3)


async def beat_forever(heartbeat: Heartbeat, every_s: float = 1.0) -> None:
    """Beats from the event loop: a loop blocked by a stuck call stops beating."""
    while True:
        heartbeat.beat()
        await asyncio.sleep(every_s)


class CachedCheck:
    def __init__(
        self,
        name: str,
        call: Callable[[], object],
        ttl_s: float = 2.0,
        timeout_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
        on_close: Callable[[], object] | None = None,
    ):
        self.on_close = on_close  # releases what the call holds (a client): close()
        self.name, self.call, self.ttl_s, self.timeout_s, self.clock = (
            name,
            call,
            ttl_s,
            timeout_s,
            clock,
        )
        self._ok = False
        self._checked: float | None = None
        self._running: threading.Thread | None = None
        self._started = 0.0  # when the running refresh began
        self._lock = threading.Lock()

    def close(self) -> None:
        if self.on_close is not None:
            self.on_close()

    def _run(self) -> None:
        try:
            ok = self.call() is not False
        except Exception as exc:  # noqa: BLE001 (any failure of the dependency is "down")
            ok = False
            log.info("dependency check failed", check=self.name, error=str(exc)[:200])
        with self._lock:
            self._ok, self._checked, self._running = ok, self.clock(), None

    def nowait(self) -> bool | None:
        """The answer without waiting at all (an event loop may call this), a refresh
        started when one is due; None before the first answer (then call it in a thread)."""
        with self._lock:
            now = self.clock()
            if self._checked is None:
                return None
            if now - self._checked < self.ttl_s:
                return self._ok
            self._refresh(now)
            return self._ok and now - self._started < self.timeout_s

    def _refresh(self, now: float) -> threading.Thread:
        """The running refresh, started if none runs (called under _lock)."""
        if self._running is None:
            self._running = threading.Thread(
                target=self._run, daemon=True, name=f"check-{self.name}"
            )
            self._started = now
            self._running.start()
        return self._running

    def __call__(self) -> bool:
        with self._lock:
            now = self.clock()
            if self._checked is not None and now - self._checked < self.ttl_s:
                return self._ok
            thread = self._refresh(now)
            known = self._checked is not None
        # With an earlier answer a probe waits only briefly for the refresh: a busy
        # dependency keeps its last answer until the refresh is older than timeout_s.
        thread.join(min(self.timeout_s, REFRESH_WAIT_S) if known else self.timeout_s)
        with self._lock:
            if not thread.is_alive():
                return self._ok
            if known and self.clock() - self._started < self.timeout_s:
                return self._ok
            return False  # hung: down until it answers


class KafkaMetadata:
    """A broker metadata request (the cheapest call that needs a working broker). Its
    AdminClient is made on the first request: librdkafka dials the brokers as soon as a
    client exists, and a process never probed need not (nor log that it cannot reach them).
    `close()` lets it go, so it stops dialling."""

    def __init__(self, settings: Settings) -> None:
        self._config = settings.kafka_config()
        self._lock = threading.Lock()
        self.admin: AdminClient | None = None

    def __call__(self, timeout_s: float) -> bool:
        from confluent_kafka.admin import AdminClient

        with self._lock:
            if self.admin is None:
                self.admin = AdminClient(self._config)
            admin = self.admin
        return bool(admin.list_topics(timeout=timeout_s).brokers)

    def close(self) -> None:
        with self._lock:
            self.admin = None  # AdminClient has no close: its last reference gone, it ends


def kafka_check(settings: Settings, timeout_s: float = 3.0) -> CachedCheck:
    """Whether a Kafka broker answers metadata (an answer reused for
    MAPSERVICE_KAFKA_CHECK_TTL_S); its `close()` releases the client."""
    metadata = KafkaMetadata(settings)
    return CachedCheck(
        "kafka",
        partial(metadata, timeout_s),
        ttl_s=settings.kafka_check_ttl_s,
        timeout_s=timeout_s,
        on_close=metadata.close,
    )


def failing_reasons(
    checks: Mapping[str, Callable[[], object]], results: Mapping[str, bool]
) -> dict[str, str]:
    """Why each failed check failed, from the checks that can say so (a `reason()`
    method returning text, as insert_health.InsertHealth has): a probe's answer names
    the cause, not only the dependency."""
    out = {}
    for name, ok in results.items():
        explain = getattr(checks.get(name), "reason", None)
        if not ok and callable(explain) and (why := explain()):
            out[name] = str(why)
    return out


def probe_report(checks: Mapping[str, Callable[[], object]]) -> dict[str, Any]:
    """A probe's answer: `ok`, each check's result and, for those that failed and can say
    why, `reasons`."""
    results = {name: bool(check()) for name, check in checks.items()}
    reasons = failing_reasons(checks, results)
    return {
        "ok": all(results.values()),
        "checks": results,
        **({"reasons": reasons} if reasons else {}),
    }
