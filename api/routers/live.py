"""Live stream of chunk changes and poses as they are stored (WebSocket)."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends, WebSocket, WebSocketDisconnect

from mapservice.core.live_messages import LiveText

from ..access import LIVE_SUBPROTOCOL, SOCKET_READ
from ..limits import origin_allowed

router = APIRouter(tags=["live"])

# RFC 6455 close codes: 1011 the server cannot serve this at all, 1013 try again later.
NO_FEED, FEED_NOT_READY = 1011, 1013


@router.websocket("/api/v1/live", dependencies=[Depends(SOCKET_READ)])
async def live(websocket: WebSocket) -> None:
    """Each message is one JSON event: {"type": "pose"|"chunk", ...} plus `sent_ms`,
    sent once the event is queryable through this API. With MAPSERVICE_API_READ_ACCESS=token
    a browser sends its token as the subprotocol `bearer.<token>` next to `mapservice.live`."""
    hub = websocket.app.state.live
    settings = websocket.app.state.settings
    if not origin_allowed(websocket.headers.get("origin"), websocket.headers.get("host"),
                          settings.api_allowed_origins):
        # Before accept: the handshake is refused (HTTP 403), no data is sent.
        await websocket.close(code=1008, reason="this origin may not open the live stream "
                                                "(MAPSERVICE_API_ALLOWED_ORIGINS)")
        return
    offered = [p.strip() for p in websocket.headers.get("sec-websocket-protocol", "").split(",")]
    await websocket.accept(subprotocol=LIVE_SUBPROTOCOL if LIVE_SUBPROTOCOL in offered else None)
    if hub is None:
        await websocket.close(code=NO_FEED, reason="this API process has no live feed")
        return
    if not hub.ready():
        await websocket.close(code=FEED_NOT_READY, reason="live feed not connected to Kafka yet; "
                              "reconnect in a few seconds")
        return
    # Each client costs a queue and a task: a bound per process, and a reason the client
    # can show (the UI reconnects with backoff on 1013, as it does while the feed starts).
    if hub.subscribers >= settings.api_max_live_clients:
        await websocket.close(code=FEED_NOT_READY, reason=(
            f"too many live clients ({settings.api_max_live_clients}, "
            "MAPSERVICE_API_MAX_LIVE_CLIENTS); try again later"))
        return
    queue = hub.subscribe()
    try:
        while True:
            message = await queue.get()
            sent_ms = time.time_ns() // 1_000_000
            if isinstance(message, LiveText):
                # As it came from the live topic, with this send's time added: no decoding
                # into a dict and encoding again, per message and viewer.
                await websocket.send_text(message.with_sent_ms(sent_ms))
            else:
                # A copy: every subscriber's queue holds the same dict, and each stamps its own send.
                await websocket.send_json({**message, "sent_ms": sent_ms})
    except WebSocketDisconnect:
        pass
    finally:
        hub.unsubscribe(queue)
