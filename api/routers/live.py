"""Live stream of chunk changes and poses as they are stored (WebSocket)."""

from __future__ import annotations

import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

router = APIRouter(tags=["live"])


@router.websocket("/api/v1/live")
async def live(websocket: WebSocket) -> None:
    """Each message is one JSON event: {"type": "pose"|"chunk", ...} plus `sent_ms`."""
    hub = websocket.app.state.live
    await websocket.accept()
    if hub is None:
        await websocket.close(code=1011, reason="live stream needs the processors in this process")
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
