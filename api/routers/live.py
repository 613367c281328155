"""Live stream of chunk changes and poses as they are stored (WebSocket)."""

from __future__ import annotations

import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

router = APIRouter(tags=["live"])

# RFC 6455 close codes: 1011 the server cannot serve this at all, 1013 try again later.
NO_FEED, FEED_NOT_READY = 1011, 1013


@router.websocket("/api/v1/live")
async def live(websocket: WebSocket) -> None:
    """Each message is one JSON event: {"type": "pose"|"chunk", ...} plus `sent_ms`,
    sent once the event is queryable through this API."""
    hub = websocket.app.state.live
    await websocket.accept()
    if hub is None:
        await websocket.close(code=NO_FEED, reason="this API process has no live feed")
        return
    if not hub.ready():
        await websocket.close(code=FEED_NOT_READY, reason="live feed not connected to Kafka yet; "
                              "reconnect in a few seconds")
        return
    queue = hub.subscribe()
    try:
        while True:
            message = await queue.get()
            # A copy: every subscriber's queue holds the same dict, and each stamps its own send.
            await websocket.send_json({**message, "sent_ms": time.time_ns() // 1_000_000})
    except WebSocketDisconnect:
        pass
    finally:
        hub.unsubscribe(queue)
