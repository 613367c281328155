"""What no route sees, before the routes: the docs pages by MAPSERVICE_API_DOCS_ACCESS and
the rate limits per credential (MAPSERVICE_API_RATE_LIMIT). Who a caller is comes from
`credentials.py`; the routes' own scopes are `access.py`'s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from fastapi import HTTPException, Request
from limits import RateLimitItem, parse_many
from limits.storage import MemoryStorage
from limits.strategies import SlidingWindowCounterRateLimiter
from starlette.types import ASGIApp, Receive, Send
from starlette.types import Scope as AsgiScope

from .admission import CALLER_KEY, deny_socket
from .credentials import (
    Caller,
    Credentials,
    bearer_token,
    client_address,
    denied,
    subprotocol_token,
    tokens_of,
)
from .limits import send_refusal

DOCS_PATHS = ("/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json")
# Not rate-limited: the kubelet's probes must never be refused for being frequent.
UNLIMITED_PATHS = ("/healthz", "/readyz")
# Who may read the docs pages while MAPSERVICE_API_DOCS_ACCESS=token: the roles this guard has
# always admitted, not every holder of the read scope (operator and robot tokens get a 403).
DOCS_ROLES = ("reader", "writer", "admin")


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
        token = bearer_token(headers.get(b"authorization", b"").decode("latin-1"))
        if token is None and scope["type"] == "websocket":
            token = subprotocol_token(headers.get(b"sec-websocket-protocol", b"").decode("latin-1"))
        address = client_address(scope.get("client"))
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
                await send_refusal(send, denied.status_code, denied.detail, denied.headers or {})
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
                        await send_refusal(send, 429, detail, {"Retry-After": str(wait)})
                    return
        await self.app(scope, receive, send)

    def _docs_denied(self, caller: Caller, valid: bool) -> HTTPException | None:
        if self.docs == "off":
            return HTTPException(
                404, "the API documentation is off (MAPSERVICE_API_DOCS_ACCESS=off)"
            )
        if not valid:
            return denied(
                401, "the bearer token is not one of this service's credentials", "invalid_token"
            )
        if caller.role in DOCS_ROLES:
            return None
        return denied(
            401 if caller.role is None else 403,
            f"the API documentation needs {tokens_of(DOCS_ROLES)} (MAPSERVICE_API_DOCS_ACCESS=token)",
        )
