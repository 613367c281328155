"""Who may do what, route by route: every route declares one access scope (a dependency
from this module), `check_routes` refuses to build an app with a route that declares none,
and `document_scopes` names each operation's scope in the OpenAPI document. The tokens, the
roles and the scopes each role grants are `credentials.py`'s; the guard middleware
(`access_guard.py`) adds what no route sees (the docs pages, rate limits).

A state-changing request must carry a JSON body (415 otherwise): a browser sends
`text/plain` and form bodies cross-site without asking first.
"""

from __future__ import annotations

from fastapi import FastAPI, HTTPException, Request, Security, WebSocket
from fastapi.exceptions import WebSocketException
from fastapi.routing import APIRoute, APIWebSocketRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from mapservice.settings import Settings

from .access_guard import DOCS_PATHS
from .context import context_of
from .credentials import (
    GRANTS,
    WHO_MAY,
    Caller,
    Scope,
    bearer_token,
    client_address,
    decide,
    denied,
    subprotocol_token,
    tokens_of,
)

STATE_CHANGING = ("POST", "PUT", "PATCH", "DELETE")


_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description=(
        f"Send {tokens_of(tuple(GRANTS))} as `Authorization: Bearer <token>`. Which roles "
        "an operation admits is its `x-mapservice-scope`; its 403 answer names them."
    ),
)
_WHAT = {
    Scope.READ: "reading",
    Scope.WRITE: "writing",
    Scope.ADMIN: "this administrative operation",
    Scope.OPERATE: (
        "editing the annotations (points of interest, zones), commanding robots or managing "
        "the incident alerts' webhooks"
    ),
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
            context_of(request.app).access,
            self.scope,
            credentials.credentials if credentials else None,
            client_address(request.client),
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
        token = bearer_token(websocket.headers.get("authorization"))
        if token is None:
            token = subprotocol_token(websocket.headers.get("sec-websocket-protocol", ""))
        try:
            return decide(
                context_of(websocket.app).access,
                self.scope,
                token,
                client_address(websocket.client),
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
        raise denied(
            403,
            f"this robot token belongs to robot {caller.robot_id!r} and writes "
            f"only as it, not as {robot_id[:80]!r}",
            "insufficient_scope",
        )


def require(caller: Caller, scope: Scope, what: str) -> None:
    """Inside a handler: a 403 unless the caller (already admitted) also holds `scope`."""
    if not caller.may(scope):
        raise denied(403, f"{what} needs {WHO_MAY[scope]}", "insufficient_scope")


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
        settings: Settings = context_of(app).settings
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
                "over MAPSERVICE_API_RATE_LIMIT, or this caller is over its share of "
                "the pool's queue (api/admission.py); Retry-After says when to try again",
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
