"""One API process's WebSocket subscribers, fed with live messages from its event loop.

The messages come from the live topic (`mapservice.core.live_messages` encodes and decodes
them); a slow subscriber loses its oldest messages, never slows the others.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence

from mapservice.core.live_messages import LiveText


class LiveHub:
    """One API process's WebSocket subscribers; fed from its event loop."""

    def __init__(self, queue_size: int = 10_000, ready: Callable[[], bool] = lambda: True) -> None:
        self._subscribers: set[asyncio.Queue] = set()
        self._feeds: set[asyncio.Queue] = set()  # the process's own consumers, not viewers
        self._queue_size = queue_size
        self.ready = ready  # whether the feed reaches this process yet (the relay reads the topic)

    def subscribe(self, viewer: bool = True) -> asyncio.Queue:
        """A queue of every message from now on; `viewer` False for a feed of this process
        (the Foxglove server's), which the cap on viewers does not count."""
        queue: asyncio.Queue = asyncio.Queue(self._queue_size)
        self._subscribers.add(queue)
        if not viewer:
            self._feeds.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue) -> None:
        self._subscribers.discard(queue)
        self._feeds.discard(queue)

    @property
    def subscribers(self) -> int:
        """The viewers (the WebSocket clients of /api/v1/live)."""
        return len(self._subscribers) - len(self._feeds)

    def publish(self, messages: Sequence[LiveText]) -> None:
        for queue in self._subscribers:
            for m in messages:
                if queue.full():
                    queue.get_nowait()  # drop the oldest: live means now
                queue.put_nowait(m)
