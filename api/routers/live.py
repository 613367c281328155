"""Live stream of chunk changes, poses and incidents as they are stored (WebSocket)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Coroutine
from typing import Any

import structlog
from fastapi import APIRouter, Depends, WebSocket, WebSocketDisconnect
from pydantic import TypeAdapter, ValidationError

from mapservice.core.live_messages import LiveText

from ..access import SOCKET_READ
from ..credentials import LIVE_SUBPROTOCOL
from ..deps import LiveHubDep, SettingsDep
from ..limits import origin_allowed

router = APIRouter(tags=["live"])
log = structlog.get_logger(__name__)

# RFC 6455 close codes: 1008 the request breaks this endpoint's rules, 1011 the server
# cannot serve this at all, 1013 try again later.
BAD_REQUEST, NO_FEED, FEED_NOT_READY = 1008, 1011, 1013

# Events per batched frame: a viewer that fell behind catches up in frames of this many
# instead of one frame of its whole queue (up to the hub's 10,000, some MB of JSON).
MAX_FRAME_EVENTS = 1000

_BOOL = TypeAdapter(bool)


@router.websocket("/api/v1/live", dependencies=[Depends(SOCKET_READ)])
async def live(
    websocket: WebSocket, hub: LiveHubDep, settings: SettingsDep, batch: str = "false"
) -> None:
    """Each message is one JSON event: {"type": "pose"|"chunk", ...} plus `sent_ms`,
    sent once the event is queryable through this API, or an incident found in them
    once stored: {"type": "incident", "ts_ms", "retracted", "incident"} (the incident as
    GET /api/v1/incidents lists it). With `?batch=true` each message is
    instead a JSON array of one or more such events, in order, each exactly as sent alone
    (its own `sent_ms`, the frame's send time): what had queued up for this viewer, at most
    1,000 per message, so a busy floor costs one send per batch rather than per event. A
    `batch` that is not a boolean (true/false, 1/0, yes/no, on/off) closes the socket
    with 1008 and a reason. With MAPSERVICE_API_READ_ACCESS=token a browser sends its
    token as the subprotocol `bearer.<token>` next to `mapservice.live`."""
    # The Host was checked for every request, this one too (api/limits.py HostCheck).
    if not origin_allowed(
        websocket.headers.get("origin"), websocket.headers.get("host"), settings.api_allowed_origins
    ):
        # Before accept: the handshake is refused (HTTP 403), no data is sent.
        await websocket.close(
            code=1008,
            reason="this origin may not open the live stream (MAPSERVICE_API_ALLOWED_ORIGINS)",
        )
        return
    offered = [p.strip() for p in websocket.headers.get("sec-websocket-protocol", "").split(",")]
    await websocket.accept(subprotocol=LIVE_SUBPROTOCOL if LIVE_SUBPROTOCOL in offered else None)
    batched = _parse_bool(batch)
    if batched is None:
        # Parsed here, not as a `bool` parameter: FastAPI refuses a bad query value on a
        # WebSocket before accept, which a client sees as a bare HTTP 403 without reason.
        await websocket.close(
            code=BAD_REQUEST,
            reason=(f"query parameter batch must be true or false, not {ascii(batch)[:40]}"),
        )
        return
    if hub is None:
        await websocket.close(code=NO_FEED, reason="this API process has no live feed")
        return
    if not hub.ready():
        await websocket.close(
            code=FEED_NOT_READY,
            reason="live feed not connected to Kafka yet; reconnect in a few seconds",
        )
        return
    # Each client costs a queue and a task: a bound per process, and a reason the client
    # can show (the UI reconnects with backoff on 1013, as it does while the feed starts).
    if hub.subscribers >= settings.api_max_live_clients:
        await websocket.close(
            code=FEED_NOT_READY,
            reason=(
                f"too many live clients ({settings.api_max_live_clients}, "
                "MAPSERVICE_API_MAX_LIVE_CLIENTS); try again later"
            ),
        )
        return
    queue = hub.subscribe()
    timeout_s = settings.api_live_send_timeout_s
    send = (_send_batches if batched else _send_each)(_Sender(websocket, timeout_s), queue)
    try:
        await _until_either(send, _drop_what_the_client_sends(websocket))
    except WebSocketDisconnect:
        pass
    except TimeoutError:
        # The client does not read: its socket and the server's buffer for it are full. Its
        # queue stops growing (the hub drops the oldest), but the connection is closed so a
        # thousand such clients hold nothing.
        log.info("live client dropped: it does not read", timeout_s=timeout_s)
        with contextlib.suppress(Exception):
            async with asyncio.timeout(1.0):
                await websocket.close(
                    code=BAD_REQUEST,
                    reason=(
                        f"this client took no message for {timeout_s:g} s "
                        "(MAPSERVICE_API_LIVE_SEND_TIMEOUT_S); read the stream, then reconnect"
                    ),
                )
    finally:
        hub.unsubscribe(queue)


async def _until_either(*steps: Coroutine[Any, Any, None]) -> None:
    """Runs `steps` together until one ends; the others are cancelled and its exception,
    if any, raised."""
    tasks = [asyncio.ensure_future(step) for step in steps]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        # Not awaited: when the server cancels this route (a shutdown), an await here would
        # be cancelled again; the tasks end at their next step.
        for task in tasks:
            task.cancel()
    for task in done:
        task.result()


async def _drop_what_the_client_sends(websocket: WebSocket) -> None:
    """Reads and drops each message the client sends (the stream takes none; the largest is
    uvicorn's ws_max_size, api/limits.py) until it closes: a message left unread stops the
    server reading the connection, so the client's close and pongs would go unseen and its
    slot stay taken until a send timed out."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000), message.get("reason"))


class _Sender:
    """The socket's send_text, each send within `timeout_s` (TimeoutError otherwise)."""

    def __init__(self, websocket: WebSocket, timeout_s: float) -> None:
        self.websocket, self.timeout_s = websocket, timeout_s

    async def send_text(self, text: str) -> None:
        async with asyncio.timeout(self.timeout_s):
            await self.websocket.send_text(text)


def _parse_bool(value: str) -> bool | None:
    """`value` as FastAPI reads a boolean query parameter (pydantic's rules), or None."""
    try:
        return _BOOL.validate_python(value)
    except ValidationError:
        return None


async def _send_each(websocket: WebSocket, queue: asyncio.Queue) -> None:
    """One message per event, as every client before `batch` expects."""
    while True:
        message = await queue.get()
        await websocket.send_text(_event_text(message, _now_ms()))


async def _send_batches(websocket: WebSocket, queue: asyncio.Queue) -> None:
    """One message per batch: the next event and whatever queued up behind it, so at
    thousands of events per second a send (a socket write) carries many of them."""
    while True:
        messages = [await queue.get()]
        while len(messages) < MAX_FRAME_EVENTS and not queue.empty():
            messages.append(queue.get_nowait())
        sent_ms = _now_ms()
        # Joined as text: each event's JSON is already there, no array to encode.
        await websocket.send_text("[" + ",".join(_event_text(m, sent_ms) for m in messages) + "]")


def _event_text(message: LiveText, sent_ms: int) -> str:
    """One event's JSON with `sent_ms` added: as it came from the live topic, with this
    send's time added, no decoding into a dict and encoding again, per message and viewer."""
    return message.with_sent_ms(sent_ms)


def _now_ms() -> int:
    return time.time_ns() // 1_000_000
