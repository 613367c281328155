"""In-process fan-out of accepted events to live subscribers (the API's WebSocket).

The history sink publishes each batch once it is stored, so a live client sees exactly
what a replay of that moment would show. Slow subscribers lose their oldest queued
messages rather than slowing the sink.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

from .events import ChunkUpdated, Envelope, PoseReported
from .wire2019 import format_timestamp


def live_message(e: Envelope) -> dict | None:
    p = e.payload
    base = {"robotId": e.robot_id, "ts_ms": e.event_time_ms, "timestamp": format_timestamp(e.event_time_ms),
            "receive_time_ms": e.receive_time_ms}
    if isinstance(p, PoseReported):
        return {"type": "pose", **base, "position": list(p.position),
                "orientation": list(p.orientation), "battery_level": p.battery_level,
                "charging": p.charging, "loaded": p.loaded,
                "path": [list(pt) for pt in p.path] if p.path is not None else None}
    if isinstance(p, ChunkUpdated):
        return {"type": "chunk", **base, "row": p.row, "column": p.column,
                "content_hash": p.content_hash.hex()}
    return None


class LiveHub:
    def __init__(self, queue_size: int = 10_000) -> None:
        self._subscribers: set[asyncio.Queue] = set()
        self._queue_size = queue_size

    def subscribe(self) -> asyncio.Queue:
        queue: asyncio.Queue = asyncio.Queue(self._queue_size)
        self._subscribers.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue) -> None:
        self._subscribers.discard(queue)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)

    def publish(self, events: Sequence[Envelope]) -> None:
        if not self._subscribers:
            return
        messages = [m for m in (live_message(e) for e in events) if m is not None]
        for queue in self._subscribers:
            for m in messages:
                if queue.full():
                    queue.get_nowait()  # drop the oldest: live means now
                queue.put_nowait(m)
