"""Bounds on what a client may send: a body limit on every route, validation errors that
never echo large input, requests only under the service's own host names, and WebSocket
connections only from the service's own pages."""

from __future__ import annotations

import asyncio
import ipaddress
import json
from collections.abc import Mapping
from urllib.parse import urlsplit

from fastapi import Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

ECHO_MAX = 200  # characters of a rejected input a reply may repeat
# The largest message a WebSocket client may send (uvicorn's `ws_max_size`, enforced by the
# websockets library as it reads and inflates a frame; one over it closes the connection
# with 1009). The API's one WebSocket, /api/v1/live, takes no message at all: uvicorn's
# 16 MiB default let each client park a message that size (inflated from a few kB with
# permessage-deflate) in a server that never reads it.
WEBSOCKET_MAX_MESSAGE_BYTES = 4 * 1024


async def send_refusal(
    send: Send, status: int, detail: str, headers: Mapping[str, str] | None = None
) -> None:
    """A JSON refusal `{"detail": ...}` sent by a middleware, before any route."""
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *((k.lower().encode(), v.encode()) for k, v in (headers or {}).items()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


async def reply_and_close(send: Send, status: int, detail: str) -> None:
    """A refusal that closes the connection (its body unread)."""
    await send_refusal(send, status, detail, {"connection": "close"})


class BodyLimit:
    """Reads at most `max_bytes` of a request body, then hands it to the app; a larger body
    is answered 413 without reading the rest (Content-Length is checked before any byte),
    one that does not arrive within `timeout_s` 408 (a client trickling its body holds a
    connection and a task). Paths under `exempt` bring their own limits (the ClickHouse
    interface's inserts)."""

    def __init__(
        self, app: ASGIApp, max_bytes: int, exempt: tuple[str, ...] = (), timeout_s: float = 30.0
    ):
        self.app, self.max_bytes, self.exempt, self.timeout_s = app, max_bytes, exempt, timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] in ("GET", "HEAD", "OPTIONS")
            or any(scope["path"] == p or scope["path"].startswith(p + "/") for p in self.exempt)
        ):
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.max_bytes):
            await self._too_large(send)
            return
        try:
            async with asyncio.timeout(self.timeout_s):
                chunks = await self._read(receive)
        except TimeoutError:
            await reply_and_close(
                send,
                408,
                f"the request body did not arrive within "
                f"{self.timeout_s:g} s (MAPSERVICE_API_BODY_TIMEOUT_S)",
            )
            return
        if chunks is None:  # the client left
            return
        if sum(map(len, chunks)) > self.max_bytes:
            await self._too_large(send)
            return
        body, sent = b"".join(chunks), False

        async def replay() -> dict:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _read(self, receive: Receive) -> list[bytes] | None:
        """The body's parts, up to the first one past max_bytes; None when the client left."""
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return None
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > self.max_bytes or not message.get("more_body"):
                return chunks

    async def _too_large(self, send: Send) -> None:
        await reply_and_close(
            send,
            413,
            # Worded as the 2019 writes' refusals (reason first): a map upload reads it.
            f"oversized: the request body is larger than {self.max_bytes} bytes "
            "(MAPSERVICE_API_MAX_BODY_BYTES)",
        )


def _short(value):
    text = value if isinstance(value, str) else json.dumps(jsonable_encoder(value), default=str)
    return value if len(text) <= ECHO_MAX else text[:ECHO_MAX] + f"... ({len(text)} characters)"


async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422, with each rejected input cut to ECHO_MAX characters."""
    errors = []
    for error in exc.errors():
        error = dict(error)
        if "input" in error:
            error["input"] = _short(error["input"])
        errors.append(error)
    return JSONResponse({"detail": jsonable_encoder(errors)}, status_code=422)


LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def _host_name(netloc: str) -> str:
    """`host[:port]` or `[v6]:port` -> the host name, lower case."""
    netloc = netloc.strip().lower()
    if netloc.startswith("["):
        return netloc[1 : netloc.find("]")] if "]" in netloc else netloc
    return netloc.rsplit(":", 1)[0] if netloc.count(":") == 1 else netloc


def allowed_hosts(settings) -> frozenset[str]:
    """The host names a live connection may be addressed to: this machine's loopback names,
    the bind address, the public base URL's host, the allowed origins' hosts and
    MAPSERVICE_API_ALLOWED_HOSTS."""
    names = {
        *LOCAL_HOSTS,
        settings.api_host.lower(),
        *(h.lower() for h in settings.api_allowed_hosts),
    }
    for url in (settings.public_base_url, *settings.api_allowed_origins):
        host = urlsplit(url).hostname
        if host:
            names.add(host.lower())
    names.discard("0.0.0.0")
    names.discard("::")
    return frozenset(names)


def _is_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def host_allowed(host: str | None, allowed: frozenset[str]) -> bool:
    """A page of another site whose name an attacker points at this address (DNS
    rebinding) reaches the service under that name: its Host is not one of ours. An IP
    address as Host is no such name (a page can only be of that address itself): the
    kubelet's probes, Prometheus and clients inside the cluster send the pod's."""
    if not host:
        return False
    name = _host_name(host)
    return name in allowed or _is_address(name)


# Answered under any Host: the kubelet asks them by the pod's address (or a name set in the
# probe), and they say only whether the process lives and is ready - nothing of the
# history. A restart loop must never follow from a mistyped MAPSERVICE_API_ALLOWED_HOSTS.
PROBE_PATHS = frozenset({"/healthz", "/readyz"})


class HostCheck:
    """Every request and WebSocket under one of the service's own host names (allowed_hosts,
    or an IP address), else refused before any other middleware or route sees it: 421
    Misdirected Request, or a WebSocket closed before it is accepted. The probes excepted."""

    def __init__(self, app: ASGIApp, allowed: frozenset[str]) -> None:
        self.app, self.allowed = app, allowed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or scope["path"] in PROBE_PATHS:
            await self.app(scope, receive, send)
            return
        host = next((v.decode("latin-1") for k, v in scope["headers"] if k == b"host"), None)
        if host_allowed(host, self.allowed):
            await self.app(scope, receive, send)
            return
        detail = (
            f"this service does not answer under the host name {(host or '')[:100]!r}; "
            "add it to MAPSERVICE_API_ALLOWED_HOSTS if it is one of the service's names"
        )
        if scope["type"] == "websocket":
            # Before accept: the handshake is refused (HTTP 403), no data is sent.
            reason = "this host name is not one of the service's (MAPSERVICE_API_ALLOWED_HOSTS)"
            await send({"type": "websocket.close", "code": 1008, "reason": reason})
            return
        await reply_and_close(send, 421, detail)


def origin_allowed(origin: str | None, host: str | None, allowed: list[str]) -> bool:
    """A browser's WebSocket from another site carries that site's Origin: only the
    service's own pages (same host) and the configured origins may connect. Clients that
    are not browsers send no Origin and are let through (they are not a CSRF vector)."""
    if not origin:
        return True
    if origin in allowed:
        return True
    return bool(host) and urlsplit(origin).netloc == host
