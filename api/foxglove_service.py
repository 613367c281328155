"""The Foxglove WebSocket server of one API process: the SDK's live server on a loopback
port of its own, fed from this process's live hub (the relay of the live topic, the same
feed as /api/v1/live), a replay server per replay client, and the gate on the public port
that admits clients by the API's rules (foxglove_gate.py). Inside the API process: the live
stream is already here, and so are the store's time-travel reads a seek makes; a process
of its own would read the live topic a second time and hold a store connection of its own
(docs/foxglove.md)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

import structlog

from mapservice.adapters.foxglove_channels import FoxgloveChannels
from mapservice.adapters.foxglove_live import FoxgloveLive
from mapservice.adapters.foxglove_replay import ReplaySession
from mapservice.adapters.foxglove_scene import FoxgloveScene
from mapservice.adapters.mcap_export import ReplaySources
from mapservice.settings import Settings

from .credentials import Credentials
from .foxglove_gate import FoxgloveGate, Upstream
from .live_hub import LiveHub

log = structlog.get_logger(__name__)

SERVER_NAME = "mapservice"


@dataclass(eq=False)
class FoxgloveService:
    """Starts and stops the live server, its feed and the gate."""

    settings: Settings
    sources: ReplaySources
    hub: LiveHub
    now_ms: Callable[[], int]
    port: int = 0  # the public port, once started
    gate: FoxgloveGate | None = None
    live: FoxgloveLive | None = None
    _server: object | None = None
    _feed: asyncio.Task[None] | None = None
    _queue: asyncio.Queue | None = field(default=None, repr=False)  # type: ignore[type-arg]

    async def start(self) -> None:
        import foxglove

        context = foxglove.Context()
        scene = FoxgloveScene(FoxgloveChannels(context), self.sources)
        self.live = FoxgloveLive(
            scene,
            self.now_ms,
            self.settings.foxglove_grid_every_s,
            self.settings.foxglove_annotations_every_s,
        )
        server = foxglove.start_server(
            name=SERVER_NAME,
            host="127.0.0.1",
            port=0,
            context=context,
            server_listener=self.live,
            message_backlog_size=self.settings.foxglove_backlog,
        )
        self._server = server
        self._queue = self.hub.subscribe(viewer=False)
        self._feed = asyncio.ensure_future(self.live.run(self._queue))
        live_port = server.port

        async def live_upstream() -> Upstream:
            return Upstream(live_port)

        self.gate = FoxgloveGate(
            self.settings,
            Credentials(self.settings),
            {"/": live_upstream, "/replay": self._replay_upstream},
        )
        self.port = await self.gate.start(self.settings.foxglove_host, self.settings.foxglove_port)
        log.info(
            "foxglove server listening",
            url=f"ws://{self.settings.foxglove_host}:{self.port}",
        )

    async def _replay_upstream(self) -> Upstream:
        """A replay session of its own for one client, over the retention window as of now;
        stopped when the client goes."""
        loop = asyncio.get_running_loop()
        now = self.now_ms()
        session = ReplaySession(
            self.sources,
            start_ms=now - self.settings.retention_ms,
            end_ms=now,
            backlog=self.settings.foxglove_backlog,
            max_speed=self.settings.foxglove_max_speed,
        )
        port = await loop.run_in_executor(None, session.start)

        async def release() -> None:
            await loop.run_in_executor(None, session.stop)

        return Upstream(port, release)

    async def stop(self) -> None:
        if self.gate is not None:
            await self.gate.stop()
        if self._feed is not None:
            self._feed.cancel()
            with contextlib.suppress(BaseException):
                await self._feed
        if self._queue is not None:
            self.hub.unsubscribe(self._queue)
        if self._server is not None:
            self._server.stop()  # type: ignore[attr-defined]
        if self.live is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.live.close)
