"""Admission: how much work the API takes on at once, so readers never starve the probes,
the live stream or (in one `serve` process) the processors.

Every costly request belongs to a pool: reads (`/api/...`) and exports
(`/api/v1/exports/...`). Analysts' queries (`/clickhouse`) are bounded by the analysts'
own query gate (mapservice/sql/query_gate.py: its threads, queue and "too many queries"
503), not here: a second pool in front of it would only hide its answer. A pool serves
`workers` requests at once and keeps at most `queue` more waiting, each for at most
`api_queue_wait_s`. Who waits is served in turns (fair_share.py): callers (a credential,
or one client address when anonymous) take turns, and within a caller its sessions (the
X-Mapservice-Session a page names itself with) do; a caller runs at most
`api_caller_concurrency` requests at once and keeps at most `api_caller_queue` waiting.
So a second tab or a second worker at one address waits its turn instead of being
refused, and a client opening many connections or naming many sessions still has one
caller's share. Refusals, before any work is done, all with Retry-After: 429 for a caller
over its share (its queue full, or pushed out of a full queue by a caller with fewer
waiting, or kept waiting too long by its own running requests), 503 for a pool full of
everyone's fair shares or with none free in time. A waiting read whose client went away
leaves the queue. One caller also has at most `api_live_clients_per_caller` live
connections. An export is sent whole within `api_export_deadline_s` or aborted: a client
that stops reading holds its slot that long at most. The probes, the UI's pages and
/metrics belong to no pool.

Pure ASGI, inside AccessGuard (which names the caller: `CALLER_KEY` in the scope). The
pools are per process: N API replicas take N times as much.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections import Counter as Tally
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import structlog
from prometheus_client import Counter, Gauge
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from mapservice.settings import Settings

from .fair_share import FairShare, Ticket

log = structlog.get_logger(__name__)

CALLER_KEY = "mapservice.caller"  # set by AccessGuard: "address:<ip>" or a credential's name
LIVE_PATH = "/api/v1/live"
# A page's (or a script's) own name for itself, so that its requests take turns with those
# of the caller's other sessions (fair_share.py); longer names are cut, none is "".
SESSION_HEADER = b"x-mapservice-session"
SESSION_MAX = 64
# A caller over its share waits this long before asking again: its own requests are
# under way, one of them will be done by then.
CALLER_RETRY_S = 1

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
    """`workers` at once, at most `queue` waiting, each at most `wait_s`; who waits is
    served in turns per caller and session (fair_share.py)."""

    def __init__(self, spec: PoolSpec, settings: Settings) -> None:
        self.spec, self.wait_s = spec, settings.api_queue_wait_s
        self.turns = FairShare(
            spec.workers,
            spec.queue,
            caller_running=settings.api_caller_concurrency,
            caller_queue=settings.api_caller_queue,
        )
        self._woken: dict[Ticket, asyncio.Future[str | None]] = {}
        ACTIVE.labels(spec.name).set(0)
        WAITING.labels(spec.name).set(0)

    @property
    def active(self) -> int:
        return self.turns.running

    @property
    def waiting(self) -> int:
        return self.turns.waiting

    async def acquire(self, ticket: Ticket, watch: LeaveWatch | None = None) -> str | None:
        """None once a worker is `ticket`'s; else why not: "caller" (over its share, at once
        or pushed out by a caller with less), "full", "waited" (none free in time),
        "caller-waited" (its own running requests kept it waiting) or "left" (the client
        went away while it waited, as `watch` noticed)."""
        offer = self.turns.offer(ticket)
        if offer.evicted is not None:
            self._wake(offer.evicted, "caller")
        if offer.refused is not None:
            self._gauge()
            return offer.refused
        if ticket.granted:
            self._gauge()
            return None
        woken: asyncio.Future[str | None] = asyncio.get_running_loop().create_future()
        self._woken[ticket] = woken
        self._gauge()
        left = watch.start() if watch is not None else None
        waits: set[asyncio.Future[str | None] | asyncio.Future[None]] = {woken}
        if left is not None:
            waits.add(left)
        try:
            await asyncio.wait(waits, timeout=self.wait_s, return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:
            self._woken.pop(ticket, None)
            if ticket.granted:
                self.release(ticket)
            else:
                self.turns.withdraw(ticket)
                self._gauge()
            raise
        self._woken.pop(ticket, None)
        if woken.done():
            return woken.result()
        # Waited too long, or its client left: out of the queue.
        own = self.turns.at_own_cap(ticket.caller)
        self.turns.withdraw(ticket)
        self._gauge()
        if left is not None and left.done():
            return "left"
        return "caller-waited" if own else "waited"

    def release(self, ticket: Ticket) -> None:
        for granted in self.turns.finish(ticket):
            self._wake(granted, None)
        self._gauge()

    def _wake(self, ticket: Ticket, why: str | None) -> None:
        woken = self._woken.get(ticket)
        if woken is not None and not woken.done():
            woken.set_result(why)

    def _gauge(self) -> None:
        ACTIVE.labels(self.spec.name).set(self.turns.running)
        WAITING.labels(self.spec.name).set(self.turns.waiting)


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
        self.pools = {name: Pool(spec, settings) for name, spec in pool_specs(settings).items()}
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
        pool = self.pools[name]
        ticket = Ticket(key, session_of(scope))
        watch = LeaveWatch(scope, receive)
        try:
            why = await pool.acquire(ticket, watch)
        finally:
            watch.stop()
        if why is not None:
            REFUSED.labels(name, why).inc()
            if why != "left":  # nobody to answer
                await self._refuse(send, pool, key, why)
            return
        try:
            if name == "export":
                await self._deadline(scope, watch.receive, send)
            else:
                await self.app(scope, watch.receive, send)
        finally:
            pool.release(ticket)

    async def _refuse(self, send: Send, pool: Pool, key: str, why: str) -> None:
        """429 when the caller is over its own share, 503 when the pool is; each with
        Retry-After and the settings an operator would change."""
        who = "credential" if not key.startswith("address:") else "client address"
        name, settings = pool.spec.name, self.settings
        if why == "caller":
            await reply(
                send,
                429,
                f"this {who} has more {name}s waiting than its share of the queue "
                f"(MAPSERVICE_API_CALLER_QUEUE={settings.api_caller_queue}); retry after "
                "the Retry-After seconds",
                retry_after=CALLER_RETRY_S,
            )
        elif why == "caller-waited":
            await reply(
                send,
                429,
                f"this {who}'s own {settings.api_caller_concurrency} running {name}s kept "
                f"this one waiting {pool.wait_s:g} s (MAPSERVICE_API_CALLER_CONCURRENCY); "
                "retry after the Retry-After seconds",
                retry_after=CALLER_RETRY_S,
            )
        else:
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


def session_of(scope: Scope) -> str:
    """The session a request names (SESSION_HEADER), at most SESSION_MAX characters."""
    for name, value in scope["headers"]:
        if name == SESSION_HEADER:
            session: str = value[:SESSION_MAX].decode("latin-1")
            return session
    return ""


class LeaveWatch:
    """Notices a client that goes away while its request waits in a queue (a page that
    cancelled a superseded read), so that the request leaves the queue instead of being
    served to nobody. Only for requests without a body: listening for the end of the
    connection means reading the request's messages first, and a body is for BodyLimit to
    read and bound. `receive` hands the app what was read meanwhile, then the rest."""

    def __init__(self, scope: Scope, receive: Receive) -> None:
        self._receive, self._read = receive, deque[Message]()
        self._bodiless = scope["method"] in ("GET", "HEAD")
        self._task: asyncio.Task[None] | None = None
        self.left: asyncio.Future[None] | None = None

    def start(self) -> asyncio.Future[None] | None:
        """Starts listening (the request waits); the future is done once the client left."""
        if not self._bodiless or self._task is not None:
            return self.left
        loop = asyncio.get_running_loop()
        self.left = loop.create_future()
        self._task = loop.create_task(self._listen())
        return self.left

    async def _listen(self) -> None:
        while True:
            message = await self._receive()
            self._read.append(message)
            if message["type"] == "http.disconnect":
                if self.left is not None and not self.left.done():
                    self.left.set_result(None)
                return
            if message.get("body") or message.get("more_body"):
                return  # a body after all: BodyLimit's to read

    def stop(self) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()

    async def receive(self) -> Message:
        if self._read:
            return self._read.popleft()
        return await self._receive()


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
