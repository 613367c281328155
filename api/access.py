"""Who may do what, in one place: every route declares one access scope (a dependency from
this module), `check_routes` refuses to build an app with a route that declares none, and
the guard middleware here adds what no route sees (the docs pages, rate limits).

Credentials are bearer tokens (`Authorization: Bearer <token>`), each with a role:

| role    | may                                   | setting                          |
| ------- | ------------------------------------- | -------------------------------- |
| reader  | read                                  | MAPSERVICE_API_READER_TOKENS     |
| writer  | read, the 2019 REST writes (robots)   | MAPSERVICE_API_WRITER_TOKENS     |
| robot   | a writer bound to one robotId: chunks | MAPSERVICE_API_ROBOT_TOKENS      |
|         | only under its own id (the handler)   | (robotId=token pairs)            |
| operator| read, edit annotations, command robots| MAPSERVICE_API_OPERATOR_TOKENS   |
| admin   | everything: deletes, the map geometry | MAPSERVICE_ADMIN_TOKEN           |
| metrics | /metrics only (the scraper)           | MAPSERVICE_API_METRICS_TOKEN     |

Reads need no credential unless MAPSERVICE_API_READ_ACCESS=token; while they are open, a
token that is none of these is ignored on reads. Elsewhere no credential is a 401, a token that is none of these
a 401 too (RFC 6750 `invalid_token`), a valid token without the scope a 403. A state-changing request must carry a JSON body (415 otherwise): a
browser sends `text/plain` and form bodies cross-site without asking first.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from fastapi import FastAPI, HTTPException, Request, Security, WebSocket
from fastapi.exceptions import WebSocketException
from fastapi.routing import APIRoute, APIWebSocketRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from limits import RateLimitItem, parse_many
from limits.storage import MemoryStorage
from limits.strategies import SlidingWindowCounterRateLimiter
from starlette.types import ASGIApp, Receive, Send
from starlette.types import Scope as AsgiScope

from mapservice.settings import Settings, robot_tokens, token_list

from .admission import CALLER_KEY, deny_socket


class Scope(str, Enum):
    PUBLIC = "public"  # probes and the UI's static pages: no data
    READ = "read"  # history and map reads: open or token (MAPSERVICE_API_READ_ACCESS)
    WRITE = "write"  # the 2019 REST writes: a writer (robot) token or the admin token
    ADMIN = "admin"  # deletes, changing the map's geometry: the admin token
    OPERATE = "operator"  # shaping the floor (annotations), commanding robots: an operator token or the admin's
    METRICS = "metrics"  # /metrics (MAPSERVICE_API_METRICS_ACCESS)


GRANTS: dict[str, frozenset[Scope]] = {
    "reader": frozenset({Scope.READ}),
    "writer": frozenset({Scope.READ, Scope.WRITE}),
    "robot": frozenset({Scope.READ, Scope.WRITE}),  # and only as itself: Caller.robot_id
    "operator": frozenset({Scope.READ, Scope.OPERATE}),
    "admin": frozenset({Scope.READ, Scope.WRITE, Scope.ADMIN, Scope.OPERATE, Scope.METRICS}),
    "metrics": frozenset({Scope.METRICS}),
}
WHO_MAY = {
    Scope.READ: "a reader, writer or admin token (MAPSERVICE_API_READER_TOKENS, "
    "MAPSERVICE_API_WRITER_TOKENS, MAPSERVICE_ADMIN_TOKEN)",
    Scope.WRITE: "a writer or robot token or the admin token (MAPSERVICE_API_WRITER_TOKENS, "
    "MAPSERVICE_API_ROBOT_TOKENS, MAPSERVICE_ADMIN_TOKEN)",
    Scope.ADMIN: "the administrator token (MAPSERVICE_ADMIN_TOKEN)",
    Scope.OPERATE: "an operator token or the admin token (MAPSERVICE_API_OPERATOR_TOKENS, "
    "MAPSERVICE_ADMIN_TOKEN); readers and robots may not shape the floor "
    "nor command robots",
    Scope.METRICS: "the metrics token or the admin token (MAPSERVICE_API_METRICS_TOKEN, "
    "MAPSERVICE_ADMIN_TOKEN)",
}
DOCS_PATHS = ("/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json")
# Not rate-limited: the kubelet's probes must never be refused for being frequent.
UNLIMITED_PATHS = ("/healthz", "/readyz")
STATE_CHANGING = ("POST", "PUT", "PATCH", "DELETE")
# Browsers connect to /api/v1/live without headers of their own: they offer these two
# WebSocket subprotocols, the second carrying the token; the first is the one accepted.
LIVE_SUBPROTOCOL = "mapservice.live"
TOKEN_SUBPROTOCOL = "bearer."


@dataclass(frozen=True)
class Caller:
    """Who sent a request: a role (None: anonymous) and a name for logs and rate limits
    that identifies the credential without revealing it."""

    role: str | None
    name: str
    robot_id: str | None = None  # a robot token's robot: it writes only as this robot

    def may(self, scope: Scope) -> bool:
        return self.role is not None and scope in GRANTS[self.role]


def _digest(token: str) -> bytes:
    # Looked up by SHA-256, not compared character by character: the time a lookup takes
    # says nothing about how much of a guessed token was right.
    return hashlib.sha256(token.encode()).digest()


class Credentials:
    """The tokens of a process, by digest. Empty settings mean no such credential."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._roles: dict[bytes, str] = {}
        self._robots = {
            _digest(token): robot
            for token, robot in robot_tokens(settings.api_robot_tokens).items()
        }
        # Later roles win when one token is listed twice: admin above all.
        for role, secret in (
            ("metrics", settings.api_metrics_token),
            ("reader", settings.api_reader_tokens),
            ("writer", settings.api_writer_tokens),
            ("operator", settings.api_operator_tokens),
            ("admin", settings.admin_token),
        ):
            for token in token_list(secret):
                self._roles[_digest(token)] = role

    def identify(self, token: str | None, address: str) -> tuple[Caller, bool]:
        """(caller, valid): anonymous by address without a token; valid False when a token
        was sent that is none of ours."""
        if not token:
            return Caller(None, f"anonymous@{address}"), True
        digest = _digest(token)
        role = self._roles.get(digest)
        if role is None and digest in self._robots:
            robot = self._robots[digest]
            return Caller("robot", f"robot:{robot}:{digest[:6].hex()}", robot), True
        if role is None:
            return Caller(None, f"anonymous@{address}"), False
        return Caller(role, f"{role}:{digest[:6].hex()}"), True


def _bearer_token(authorization: str | None) -> str | None:
    if not authorization:
        return None
    scheme, _, token = authorization.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def _subprotocol_token(offered: str) -> str | None:
    """A browser's token on a WebSocket: the subprotocol `bearer.<token>`."""
    for protocol in offered.split(","):
        protocol = protocol.strip()
        if protocol.startswith(TOKEN_SUBPROTOCOL):
            return protocol[len(TOKEN_SUBPROTOCOL) :] or None
    return None


def _address(client) -> str:
    """The client's host from an ASGI (host, port) pair or Starlette's Address."""
    return client[0] if client else "unknown"


def _denied(status: int, detail: str, error: str | None = None) -> HTTPException:
    challenge = 'Bearer realm="mapservice"' + (f', error="{error}"' if error else "")
    return HTTPException(status, detail, headers={"WWW-Authenticate": challenge})


def decide(
    credentials: Credentials, scope: Scope, token: str | None, address: str, what: str
) -> Caller:
    """The caller if `token` opens `scope`; else the HTTPException to answer (401, 403, 404)."""
    settings = credentials.settings
    caller, valid = credentials.identify(token, address)
    if scope is Scope.PUBLIC:
        return caller
    if scope is Scope.METRICS:
        if settings.metrics_access == "off":
            raise HTTPException(404, "metrics are off (MAPSERVICE_API_METRICS_ACCESS=off)")
        if settings.metrics_access == "open":
            return caller
    if scope is Scope.READ and settings.api_read_access == "open":
        # Open means open: a stale token (a browser's, a robot's after a rotation) does not
        # turn away a read anyone may make; its writes still get the 401 that says so.
        return caller
    if not valid:
        raise _denied(
            401, "the bearer token is not one of this service's credentials", "invalid_token"
        )
    if caller.role is None:
        raise _denied(401, f"{what} needs {WHO_MAY[scope]}: send 'Authorization: Bearer <token>'")
    if not caller.may(scope):
        raise _denied(
            403,
            f"this {caller.role} token may not: {what} needs {WHO_MAY[scope]}",
            "insufficient_scope",
        )
    return caller


_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description=(
        "A reader, writer (robot) or admin token: `Authorization: Bearer <token>`. Which one an "
        "operation needs is its `x-mapservice-scope`."
    ),
)
_WHAT = {
    Scope.READ: "reading",
    Scope.WRITE: "writing",
    Scope.ADMIN: "this administrative operation",
    Scope.OPERATE: "editing the annotations (points of interest, zones) or commanding robots",
    Scope.METRICS: "reading the metrics",
}


def _is_json(content_type: str | None) -> bool:
    media = (content_type or "").split(";", 1)[0].strip().lower()
    return media == "application/json" or (
        media.startswith("application/") and media.endswith("+json")
    )


def _changes_state_without_json(method: str, headers) -> bool:
    """POST, PUT and PATCH must say JSON; a DELETE only when it carries a body."""
    if method not in STATE_CHANGING:
        return False
    if (
        method == "DELETE"
        and headers.get("content-length", "0") == "0"
        and "transfer-encoding" not in headers
    ):
        return False
    return not _is_json(headers.get("content-type"))


class Need:
    """The dependency a route declares its scope with: `dependencies=[Depends(READ)]`, or
    `caller: Caller = Depends(WRITE)` where the handler uses who called."""

    def __init__(self, scope: Scope) -> None:
        self.scope = scope

    def __call__(
        self, request: Request, credentials: HTTPAuthorizationCredentials | None = Security(_bearer)
    ) -> Caller:
        caller = decide(
            request.app.state.access,
            self.scope,
            credentials.credentials if credentials else None,
            _address(request.client),
            _WHAT[self.scope],
        )
        if _changes_state_without_json(request.method, request.headers):
            raise HTTPException(
                415,
                f"{request.method} takes a JSON body: send it with "
                "'Content-Type: application/json'",
            )
        return caller

    def __repr__(self) -> str:
        return f"Need({self.scope.value})"


class Public:
    """The scope of routes that serve no data (probes, the UI's pages): no credential.
    Async: a sync dependency would take a thread of the pool the reads use, and the probes
    must answer while every one of those is busy."""

    scope = Scope.PUBLIC

    async def __call__(self) -> None:
        return None


class NeedSocket:
    """The scope of a WebSocket route. Browsers cannot set headers on a WebSocket, so the
    token may also come as the subprotocol `bearer.<token>` (next to LIVE_SUBPROTOCOL)."""

    def __init__(self, scope: Scope) -> None:
        self.scope = scope

    def __call__(self, websocket: WebSocket) -> Caller:
        token = _bearer_token(websocket.headers.get("authorization"))
        offered = [
            p.strip() for p in websocket.headers.get("sec-websocket-protocol", "").split(",")
        ]
        for protocol in offered:
            if token is None and protocol.startswith(TOKEN_SUBPROTOCOL):
                token = protocol[len(TOKEN_SUBPROTOCOL) :]
        try:
            return decide(
                websocket.app.state.access,
                self.scope,
                token,
                _address(websocket.client),
                "the live stream",
            )
        except HTTPException as exc:
            # Before accept: the handshake is refused (HTTP 403 to the client).
            raise WebSocketException(code=1008, reason=str(exc.detail)[:120]) from None


PUBLIC, READ, WRITE, ADMIN, METRICS = (
    Public(),
    Need(Scope.READ),
    Need(Scope.WRITE),
    Need(Scope.ADMIN),
    Need(Scope.METRICS),
)
OPERATE = Need(Scope.OPERATE)
SOCKET_READ = NeedSocket(Scope.READ)


def require_robot(caller: Caller, robot_id: str) -> None:
    """Inside a write handler: a 403 when a robot token writes under another robot's id."""
    if caller.robot_id is not None and caller.robot_id != robot_id:
        raise _denied(
            403,
            f"this robot token belongs to robot {caller.robot_id!r} and writes "
            f"only as it, not as {robot_id[:80]!r}",
            "insufficient_scope",
        )


def require(caller: Caller, scope: Scope, what: str) -> None:
    """Inside a handler: a 403 unless the caller (already admitted) also holds `scope`."""
    if not caller.may(scope):
        raise _denied(403, f"{what} needs {WHO_MAY[scope]}", "insufficient_scope")


# --- every route declares its scope ---------------------------------------------------------


def all_routes(app: FastAPI) -> list:
    """Every route of the app, those of included routers too (FastAPI >= 0.16x keeps an
    included router as one entry of app.routes)."""
    try:
        from fastapi.routing import iter_route_contexts
    except ImportError:  # an older FastAPI flattens included routers itself
        return list(app.routes)
    return [context.original_route for context in iter_route_contexts(app.routes)]


def route_scope(route) -> Scope | None:
    """The scope a route declares (None: none), found among its dependencies."""
    todo = list(route.dependant.dependencies)
    while todo:
        dep = todo.pop()
        if isinstance(dep.call, (Need, Public, NeedSocket)):
            return dep.call.scope
        todo.extend(dep.dependencies)
    return None


def check_routes(app: FastAPI) -> None:
    """Refuses an app with a route that declares no scope: a new endpoint is never open by
    omission. The docs pages are guarded by path (AccessGuard)."""
    missing = [
        f"{sorted(getattr(r, 'methods', None) or ['WS'])} {r.path}"
        for r in all_routes(app)
        if isinstance(r, (APIRoute, APIWebSocketRoute))
        and r.path not in DOCS_PATHS
        and route_scope(r) is None
    ]
    if missing:
        raise RuntimeError(f"routes without an access scope (api/access.py): {missing}")


def document_scopes(app: FastAPI) -> None:
    """The OpenAPI document names each operation's scope (`x-mapservice-scope`) and its
    security: none for public ones, optional for reads while reading is open."""
    build = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()
        settings: Settings = app.state.settings
        scopes = {
            (method.lower(), r.path): route_scope(r)
            for r in all_routes(app)
            if isinstance(r, APIRoute)
            for method in r.methods
        }
        for path, operations in schema.get("paths", {}).items():
            for method, operation in operations.items():
                scope = scopes.get((method, path))
                if scope is None:
                    continue
                operation["x-mapservice-scope"] = scope.value
                responses = operation.setdefault("responses", {})
                for status, description in _refusals(scope, method, settings):
                    responses.setdefault(status, {"description": description})
                if scope is Scope.PUBLIC:
                    operation["security"] = []
                elif scope is Scope.READ and settings.api_read_access == "open":
                    operation["security"] = [{}, {"bearer": []}]
                else:
                    operation["security"] = [{"bearer": []}]
        return schema

    app.openapi = openapi


def _refusals(scope: Scope, method: str, settings: Settings) -> list[tuple[str, str]]:
    """The answers this module may give an operation, for its OpenAPI `responses`."""
    out = []
    if scope is not Scope.PUBLIC and not (
        scope is Scope.READ and settings.api_read_access == "open"
    ):
        out += [
            ("401", "no credential, or a token that is none of this service's"),
            ("403", f"the token lacks the `{scope.value}` scope: {WHO_MAY.get(scope, '')}"),
        ]
    if method.upper() in ("POST", "PUT", "PATCH"):
        out.append(("415", "the body is not sent as application/json"))
    if scope is not Scope.PUBLIC:
        out.append(
            (
                "429",
                "over MAPSERVICE_API_RATE_LIMIT, or this caller has "
                "MAPSERVICE_API_CALLER_CONCURRENCY requests under way; Retry-After "
                "says when to try again",
            )
        )
        out.append(
            (
                "503",
                "the API's pool for this kind of request is full (api/admission.py); "
                "Retry-After says when to try again",
            )
        )
    return out


# --- what no route sees: the docs pages, rate limits -----------------------------------------


class AccessGuard:
    """Pure ASGI, before the routes: the docs pages by MAPSERVICE_API_DOCS_ACCESS, and rate
    limits per credential (per client address for anonymous callers and wrong tokens, so
    guessing tokens does not open new buckets): 429 with Retry-After."""

    def __init__(
        self,
        app: ASGIApp,
        credentials: Credentials,
        sql_path: str = "",
        sql_identify: Callable[[Request], str | None] | None = None,
    ) -> None:
        self.app, self.credentials = app, credentials
        # The analysts' ClickHouse interface authenticates with its own credential (HTTP
        # Basic, X-ClickHouse-User/-Key): its limits count per analyst credential, not per
        # address (an analyst on several machines would get the limit on each).
        self.sql_path, self.sql_identify = sql_path, sql_identify
        settings = credentials.settings
        self.docs = settings.docs_access
        self.limits: list[RateLimitItem] = (
            parse_many(settings.api_rate_limit) if settings.api_rate_limit.strip() else []
        )
        # In this process's memory: with N API replicas behind a balancer a client gets up
        # to N times the limit (a shared storage would be one more moving part).
        self.limiter = SlidingWindowCounterRateLimiter(MemoryStorage())

    async def __call__(self, scope: AsgiScope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        headers = dict(scope["headers"])
        token = _bearer_token(headers.get(b"authorization", b"").decode("latin-1"))
        if token is None and scope["type"] == "websocket":
            token = _subprotocol_token(
                headers.get(b"sec-websocket-protocol", b"").decode("latin-1")
            )
        address = _address(scope.get("client"))
        caller, valid = self.credentials.identify(token, address)
        key = caller.name if valid and caller.role else f"address:{address}"
        if (
            self.sql_identify is not None
            and scope["type"] == "http"
            and (path == self.sql_path or path.startswith(self.sql_path + "/"))
        ):
            key = self.sql_identify(Request(scope)) or key
        scope[CALLER_KEY] = key  # for the pools' per-caller caps (api/admission.py)
        if path in DOCS_PATHS and self.docs != "open" and scope["type"] == "http":
            denied = self._docs_denied(caller, valid)
            if denied is not None:
                await _reply(send, denied.status_code, denied.detail, denied.headers or {})
                return
        if self.limits and path not in UNLIMITED_PATHS:
            for item in self.limits:
                if not self.limiter.hit(item, key):
                    reset = self.limiter.get_window_stats(item, key).reset_time
                    wait = max(1, math.ceil(reset - time.time()))
                    detail = (
                        f"more than {item} requests from this "
                        f"{'address' if key.startswith('address:') else 'credential'}; retry in "
                        f"{wait} s (MAPSERVICE_API_RATE_LIMIT)"
                    )
                    if scope["type"] == "websocket":
                        await deny_socket(scope, send, 429, detail, retry_after=wait)
                    else:
                        await _reply(send, 429, detail, {"Retry-After": str(wait)})
                    return
        await self.app(scope, receive, send)

    def _docs_denied(self, caller: Caller, valid: bool) -> HTTPException | None:
        if self.docs == "off":
            return HTTPException(
                404, "the API documentation is off (MAPSERVICE_API_DOCS_ACCESS=off)"
            )
        if not valid:
            return _denied(
                401, "the bearer token is not one of this service's credentials", "invalid_token"
            )
        if caller.role in ("reader", "writer", "admin"):
            return None
        return _denied(
            401 if caller.role is None else 403,
            f"the API documentation needs {WHO_MAY[Scope.READ]} (MAPSERVICE_API_DOCS_ACCESS=token)",
        )


async def _reply(send: Send, status: int, detail: str, headers: dict[str, str]) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *((k.lower().encode(), v.encode()) for k, v in headers.items()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
