"""The live Foxglove server's feed: one scene (foxglove_scene.py) on one SDK context, drawn
at start from the store (the floor, every robot's latest pose and the annotations, as at
now) and then moved by the live stream the replay UI's WebSocket gets too (the API's
`LiveHub`, fed by the live topic's relay): each pose and chunk write as it is stored, each
incident as the processors announce it. The floor's grid goes out at most every
`foxglove_grid_every_s`; zones and points of interest, conflicts and VDA 5050 facts are
re-read every `foxglove_annotations_every_s` (they are not on the live topic).

Every change of the scene happens on one worker thread of its own (store reads, protobuf
building and the SDK's logging are not the event loop's work); the SDK's subscribe
callback asks for its channel's re-send there too, paced (foxglove_resends.py: a flood of
subscribes costs one re-send per channel a second, not one per message).

May depend on: the ports (reads through the scene), the live messages."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import structlog
from foxglove.websocket import ServerListener

from mapservice.adapters.foxglove_messages import pose_row_of_live
from mapservice.adapters.foxglove_resends import PacedResends
from mapservice.adapters.foxglove_scene import ChunkChange, FoxgloveScene

log = structlog.get_logger(__name__)

# Live messages handed to the worker at once: a burst is drawn in batches, the floor once per batch.
_BATCH = 2000


class FoxgloveLive(ServerListener):
    """Feeds one scene from a queue of live messages (`run`); the SDK's `ServerListener`."""

    def __init__(
        self,
        scene: FoxgloveScene,
        now_ms: Callable[[], int],
        grid_every_s: float = 1.0,
        annotations_every_s: float = 5.0,
    ) -> None:
        self.scene, self.now_ms = scene, now_ms
        self.grid_every_s, self.annotations_every_s = grid_every_s, annotations_every_s
        self.worker = ThreadPoolExecutor(1, thread_name_prefix="foxglove-live")
        self.applied = 0  # live messages drawn (tests, metrics)
        self.resends = PacedResends()
        self._last_grid = 0.0
        self._last_annotations = 0.0

    # --- the SDK's ServerListener -------------------------------------------------------

    def on_subscribe(self, client: Any, channel: Any) -> None:
        """A client subscribed: the channel's current message again (on the worker; one
        sent less than a second ago goes again with the feed's tick when that is up)."""
        if self.resends.ask(str(channel.topic)):
            with contextlib.suppress(RuntimeError):  # shut down: nothing to send
                self.worker.submit(self._guarded, self._resend_due)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        return None

    # --- the feed -----------------------------------------------------------------------

    async def run(self, queue: asyncio.Queue[Mapping[str, Any]]) -> None:
        """Draws the scene at now, then every message of `queue` (until cancelled)."""
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self.worker, self._guarded, self._draw_now)
        tick = min(self.grid_every_s, self.annotations_every_s, self.resends.every_s)
        while True:
            batch: list[Mapping[str, Any]] = []
            try:
                async with asyncio.timeout(tick):
                    batch.append(await queue.get())
            except TimeoutError:
                pass
            while batch and len(batch) < _BATCH and not queue.empty():
                batch.append(queue.get_nowait())
            await loop.run_in_executor(self.worker, self._guarded, self._apply, batch)

    def close(self) -> None:
        self.worker.shutdown(wait=True, cancel_futures=True)

    def _guarded(self, work: Callable[..., None], *args: Any) -> None:
        # The feed outlives a failed read (the store busy, restarting): logged, the next
        # batch and tick go on.
        try:
            work(*args)
        except Exception as exc:
            log.warning("foxglove live feed step failed", error=str(exc))

    def _resend_due(self) -> None:
        for topic in self.resends.due():
            self.scene.resend(topic)

    def _draw_now(self) -> None:
        self.scene.draw_at(self.now_ms())
        self._last_grid = self._last_annotations = time.monotonic()

    def _apply(self, batch: list[Mapping[str, Any]]) -> None:
        changes: list[ChunkChange] = []
        for message in batch:
            kind = message.get("type")
            if kind == "pose":
                if changes:  # in the stream's order: the writes before this pose first
                    self.scene.chunk_changes(changes)
                    changes = []
                self.scene.pose(pose_row_of_live(message))
            elif kind == "incident":
                try:
                    self.scene.findings.live_incident(message)
                except (KeyError, TypeError, ValueError) as exc:  # the batch's others go on
                    log.warning("foxglove live feed: bad incident message", error=repr(exc))
            elif kind == "chunk":
                changes.append(
                    ChunkChange(
                        row=int(message["row"]),
                        column=int(message["column"]),
                        robot_id=str(message["robotId"]),
                        content_hash=str(message["content_hash"]),
                        ts_ms=int(message["ts_ms"]),
                    )
                )
        self.scene.chunk_changes(changes)
        self.applied += len(batch)
        now = time.monotonic()
        if self.scene.floor_dirty and now - self._last_grid >= self.grid_every_s:
            self.scene.grid()
            self._last_grid = now
        if now - self._last_annotations >= self.annotations_every_s:
            now_ms = self.now_ms()
            self.scene.annotations_at(now_ms)
            self.scene.findings.reread(now_ms)
            self._last_annotations = now
        self._resend_due()
