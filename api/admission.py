"""Admission: how much work the API takes on at once, so readers never starve the probes,
the live stream or (in one `serve` process) the processors.

Every costly request belongs to a pool: reads (`/api/...`) and exports
(`/api/v1/exports/...`). Analysts' queries (`/clickhouse`) are bounded by the analysts'
own query gate (mapservice/sql/query_gate.py: its threads, queue and "too many queries"
503), not here: a second pool in front of it would only hide its answer. A pool serves `workers` requests at once and keeps
at most `queue` more waiting, each for at most `api_queue_wait_s`; beyond that the answer is
503 with Retry-After, before any work is done. On top of the pools, one credential (or
one client address when anonymous) may have at most `api_caller_concurrency` costly
requests running or queued (429 beyond) and `api_live_clients_per_caller` live
connections, so one client cannot fill a pool on its own. An export is sent whole within
`api_export_deadline_s` or aborted: a client that stops reading holds its slot that long
at most. The probes, the UI's pages and /metrics belong to no pool.

Pure ASGI, inside AccessGuard (which names the caller: `CALLER_KEY` in the scope). The
pools are per process: N API replicas take N times as much.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections import Counter as Tally
from collections.abc import Callable
from dataclasses import dataclass

import structlog
from prometheus_client import Counter, Gauge
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from mapservice.settings import Settings

log = structlog.get_logger(__name__)

CALLER_KEY = "mapservice.caller"  # set by AccessGuard: "address:<ip>" or a credential's name
LIVE_PATH = "/api/v1/live"

ACTIVE = Gauge("mapservice_api_pool_active", "Requests a pool is serving", ["pool"])
WAITING = Gauge("mapservice_api_pool_waiting", "Requests waiting in a pool's queue", ["pool"])
REFUSED = Counter(
    "mapservice_api_refused_total",
    "Requests refused by admission control, by pool and why",
    ["pool", "why"],
)


@dataclass(frozen=True)
class PoolSpec:
    name: str
    workers: int
    queue: int
    settings: str  # the settings that size it, named in a refusal


class Pool:
    """`workers` at once, at most `queue` waiting, each at most `wait_s`."""

    def __init__(self, spec: PoolSpec, wait_s: float) -> None:
        self.spec, self.wait_s = spec, wait_s
        self.active = 0
        self.waiting = 0
        self._free = asyncio.Semaphore(spec.workers)
        ACTIVE.labels(spec.name).set(0)
        WAITING.labels(spec.name).set(0)

    async def acquire(self) -> str | None:
        """None once a worker is ours; else why not (queue full, or waited too long)."""
        if self._free.locked():
            if self.waiting >= self.spec.queue:
                return "full"
            self.waiting += 1
            WAITING.labels(self.spec.name).inc()
            try:
                async with asyncio.timeout(self.wait_s):
                    await self._free.acquire()
            except TimeoutError:
                return "waited"
            finally:
                self.waiting -= 1
                WAITING.labels(self.spec.name).dec()
        else:
            await self._free.acquire()
        self.active += 1
        ACTIVE.labels(self.spec.name).inc()
        return None

    def release(self) -> None:
        self.active -= 1
        ACTIVE.labels(self.spec.name).dec()
        self._free.release()


def pool_specs(settings: Settings) -> dict[str, PoolSpec]:
    return {
        "read": PoolSpec(
            "read",
            settings.api_read_workers,
            settings.api_read_queue,
            "MAPSERVICE_API_READ_WORKERS, MAPSERVICE_API_READ_QUEUE",
        ),
        "export": PoolSpec(
            "export",
            settings.api_export_workers,
            settings.api_export_queue,
            "MAPSERVICE_API_EXPORT_WORKERS, MAPSERVICE_API_EXPORT_QUEUE",
        ),
    }


def default_pool_of(path: str) -> str | None:
    """The pool a path's requests take (None: none, e.g. the probes and the UI's pages)."""
    if path.startswith("/api/v1/exports/"):
        return "export"
    if path.startswith("/api/"):
        return "read"
    return None


class AdmissionControl:
    """The pools, the per-caller caps and the exports' deadline (module docstring).

    `pool_of` maps a path to a pool name; None leaves a path out (it brings its own bounds
    or costs nothing)."""

    def __init__(
        self,
        app: ASGIApp,
        settings: Settings,
        pool_of: Callable[[str], str | None] = default_pool_of,
    ) -> None:
        self.app, self.settings, self.pool_of = app, settings, pool_of
        self.pools = {
            name: Pool(spec, settings.api_queue_wait_s)
            for name, spec in pool_specs(settings).items()
        }
        self.per_caller: Tally[str] = Tally()
        self.live_per_caller: Tally[str] = Tally()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket" and scope["path"] == LIVE_PATH:
            await self._live(scope, receive, send)
            return
        name = self.pool_of(scope["path"]) if scope["type"] == "http" else None
        if name is None:
            await self.app(scope, receive, send)
            return
        key = scope.get(CALLER_KEY) or "address:unknown"
        cap = self.settings.api_caller_concurrency
        if self.per_caller[key] >= cap:
            REFUSED.labels(name, "caller").inc()
            who = "credential" if not key.startswith("address:") else "client address"
            await reply(
                send,
                429,
                f"this {who} already has {cap} reads or exports running "
                "or queued; wait for one to finish "
                "(MAPSERVICE_API_CALLER_CONCURRENCY)",
                retry_after=1,
            )
            return
        self.per_caller[key] += 1
        try:
            pool = self.pools[name]
            why = await pool.acquire()
            if why is not None:
                REFUSED.labels(name, why).inc()
                busy = (
                    f"{pool.spec.workers} running and {pool.spec.queue} waiting"
                    if why == "full"
                    else f"none free within {pool.wait_s:g} s (MAPSERVICE_API_QUEUE_WAIT_S)"
                )
                await reply(
                    send,
                    503,
                    f"the API's {name} pool is busy ({busy}); retry after "
                    f"the Retry-After seconds ({pool.spec.settings})",
                    retry_after=max(1, math.ceil(pool.wait_s / 5)),
                )
                return
            try:
                if name == "export":
                    await self._deadline(scope, receive, send)
                else:
                    await self.app(scope, receive, send)
            finally:
                pool.release()
        finally:
            self.per_caller[key] -= 1
            if not self.per_caller[key]:
                del self.per_caller[key]

    async def _deadline(self, scope: Scope, receive: Receive, send: Send) -> None:
        """The export whole within api_export_deadline_s, or aborted: before its first
        byte a 503 that says so; after it the connection is cut (the client sees a
        truncated body, never a complete-looking one)."""
        started = False

        async def tracking(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        deadline = self.settings.api_export_deadline_s
        try:
            async with asyncio.timeout(deadline):
                await self.app(scope, receive, tracking)
        except TimeoutError:
            REFUSED.labels("export", "deadline").inc()
            log.warning(
                "export aborted at its deadline",
                path=scope["path"],
                deadline_s=deadline,
                started=started,
            )
            if not started:
                await reply(
                    send,
                    503,
                    f"the export did not finish within {deadline:g} s "
                    "(MAPSERVICE_API_EXPORT_DEADLINE_S); ask for a shorter window",
                    retry_after=1,
                )
            # Started: returning without the body's end makes the server close the connection.

    async def _live(self, scope: Scope, receive: Receive, send: Send) -> None:
        key = scope.get(CALLER_KEY) or "address:unknown"
        cap = self.settings.api_live_clients_per_caller
        if self.live_per_caller[key] >= cap:
            REFUSED.labels("live", "caller").inc()
            await deny_socket(
                scope,
                send,
                429,
                f"this client already has {cap} live "
                "connections (MAPSERVICE_API_LIVE_CLIENTS_PER_CALLER); close one "
                "or retry later",
                retry_after=5,
            )
            return
        self.live_per_caller[key] += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.live_per_caller[key] -= 1
            if not self.live_per_caller[key]:
                del self.live_per_caller[key]


def _headers(body: bytes, retry_after: int | None) -> list[tuple[bytes, bytes]]:
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if retry_after is not None:
        headers.append((b"retry-after", str(retry_after).encode()))
    return headers


async def reply(send: Send, status: int, detail: str, retry_after: int | None = None) -> None:
    """A JSON refusal `{"detail": ...}`, with Retry-After when given."""
    body = json.dumps({"detail": detail}).encode()
    await send(
        {"type": "http.response.start", "status": status, "headers": _headers(body, retry_after)}
    )
    await send({"type": "http.response.body", "body": body})


async def deny_socket(
    scope: Scope, send: Send, status: int, detail: str, retry_after: int | None = None
) -> None:
    """Refuses a WebSocket handshake with an HTTP answer and a JSON reason where the server
    can send one (the ASGI denial-response extension: uvicorn, Starlette's TestClient);
    else with a close before accept (HTTP 403 to the client)."""
    if "websocket.http.response" in (scope.get("extensions") or {}):
        body = json.dumps({"detail": detail}).encode()
        await send(
            {
                "type": "websocket.http.response.start",
                "status": status,
                "headers": _headers(body, retry_after),
            }
        )
        await send({"type": "websocket.http.response.body", "body": body})
    else:
        await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
