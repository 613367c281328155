"""A replay client's own Foxglove server: the history's retention window as the data's
start and end (the SDK's playback-control capability), driven by the app's own controls.
A seek to T draws the floor, the robots and the annotations at T (foxglove_scene.py: as
`/api/v1/map?at=` and `/api/v1/robots?at=` read them); play at a speed streams the stored
chunk writes, poses, incidents, conflicts and VDA 5050 facts in event-time order, tick after
tick, every one of them whatever the speed. Playback follows the wall clock: a tick plays
what the speed covers since the last one, so slow reads (a loaded machine) make the windows
longer, not the playback slower; only past `MAX_TICK_WINDOWS` nominal windows a tick does the
playback fall behind (none is skipped then either); pause stops. A client's requests
cost bounded work however many it sends: the speed is held to `max_speed` (a step reads
at most that many seconds of history per second; a NaN or non-positive speed keeps the
one before), a seek not yet drawn is replaced by a later one (only the latest is
drawn), and its subscribes re-send each channel at most once a second (foxglove_resends.py).

Each session has its own SDK context and server (a loopback port the gate pipes one client
to): the protocol's playback state is the server's, so two clients would otherwise fight
over one playhead. One player thread per session does the store reads and the logging.

May depend on: the ports (reads through the scene and the replay sources)."""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

import structlog
from foxglove.websocket import ServerListener

from mapservice.adapters.foxglove_channels import FoxgloveChannels
from mapservice.adapters.foxglove_messages import window_changes, window_poses
from mapservice.adapters.foxglove_resends import PacedResends
from mapservice.adapters.foxglove_scene import ChunkChange, FoxgloveScene
from mapservice.adapters.mcap_export import ReplaySources
from mapservice.core.ports import ChunkRow
from mapservice.settings.foxglove import FoxgloveSettings

log = structlog.get_logger(__name__)

_NS_PER_MS = 1_000_000
TICK_S = 0.1  # wall time per playback step
# A tick plays at most this many ticks' worth of history (a store read of bounded size);
# a playback further behind the wall clock than that falls behind rather than reading more.
MAX_TICK_WINDOWS = 8
# A seek's picture goes out this long after the seek's answer (the SDK sends the answer on
# its control queue as the callback returns; the picture must not overtake it, the app
# clears what it holds on a seek).
_AFTER_ANSWER_S = 0.02
# The fastest playback (history seconds a wall second), the setting's own default.
DEFAULT_MAX_SPEED: float = FoxgloveSettings.model_fields["foxglove_max_speed"].default


@dataclass
class Playhead:
    """Where the playback is and how it moves (read and set under the session's lock)."""

    at_ms: int
    speed: float = 1.0
    playing: bool = False
    ended: bool = False
    wall_s: float = 0.0  # while playing: the monotonic instant `at_ms` stands for


class ReplaySession(ServerListener):
    """One client's replay: its SDK server (`start` returns its port) and its player."""

    def __init__(
        self,
        sources: ReplaySources,
        start_ms: int,
        end_ms: int,
        backlog: int = 1024,
        max_speed: float = DEFAULT_MAX_SPEED,
    ) -> None:
        self.sources = sources
        self.start_ms, self.end_ms, self.backlog = start_ms, end_ms, backlog
        self.max_speed = max_speed
        self.playhead = Playhead(at_ms=end_ms)
        self.lock = threading.Lock()
        # The player's work: "seek" (draws `_seek_to`), "resend" (what `resends` has due),
        # "stop"; each is queued only when none like it waits, so the queue stays short.
        self.commands: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.resends = PacedResends()
        self._seek_to: int | None = None  # the latest seek not drawn yet (under `lock`)
        self.scene: FoxgloveScene | None = None
        self.server: Any = None
        self.sent_changes = 0  # chunk writes played (tests)
        self._subscribed = threading.Event()  # the client's first subscription came
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove-replay", daemon=True)

    def start(self) -> int:
        import foxglove
        from foxglove.websocket import Capability

        context = foxglove.Context()
        self.scene = FoxgloveScene(FoxgloveChannels(context), self.sources)
        # Every robot's channels before the client connects (declare_robots_at says why).
        robots = self.scene.declare_robots_at(self.end_ms)
        log.debug("foxglove replay session channels declared", robots=robots)
        self.server = foxglove.start_server(
            name="mapservice replay",
            host="127.0.0.1",
            port=0,
            context=context,
            server_listener=self,
            capabilities=[Capability.PlaybackControl, Capability.Time],
            playback_time_range=(self.start_ms * _NS_PER_MS, self.end_ms * _NS_PER_MS),
            message_backlog_size=self.backlog,
        )
        self._thread.start()
        return int(self.server.port)

    def stop(self) -> None:
        self._stopping.set()
        self.commands.put(("stop", None))
        if self._thread.is_alive():
            self._thread.join(10.0)
        if self.server is not None:
            self.server.stop()

    # --- the SDK's ServerListener (its threads) -----------------------------------------

    def on_subscribe(self, client: Any, channel: Any) -> None:
        # The first picture (at the window's end: now) is drawn once the client subscribed,
        # not as the server starts: robot channels made while the client was still being
        # connected to the SDK's server were, in about one session of seven, advertised to
        # it and subscribed but never sent (their robots missing from every frame after).
        if not self._subscribed.is_set():
            self._subscribed.set()
            with self.lock:
                self._seek(self.end_ms)
        if self.resends.ask(str(channel.topic)):
            self.commands.put(("resend", None))

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        return None

    def on_playback_control_request(self, request: Any) -> Any:
        from foxglove.websocket import PlaybackCommand

        with self.lock:
            head = self.playhead
            head.speed = _speed(float(request.playback_speed), head.speed, self.max_speed)
            head.playing = request.playback_command == PlaybackCommand.Play
            seek = request.seek_time
            if seek is not None:
                self._subscribed.set()  # its own seek's picture, not the first one, after it
                head.at_ms = min(max(int(seek) // _NS_PER_MS, self.start_ms), self.end_ms)
                head.ended = False
                self._seek(head.at_ms)
            if head.playing and head.at_ms >= self.end_ms:
                head.playing, head.ended = False, True
            head.wall_s = time.monotonic()  # playing from here, at this speed, from now
            return self._state(did_seek=seek is not None, request_id=request.request_id)

    def _seek(self, at_ms: int) -> None:
        """The picture at `at_ms` is to be drawn (replacing a seek not drawn yet); under
        `lock`."""
        if self._seek_to is None:
            self.commands.put(("seek", None))
        self._seek_to = at_ms

    def _state(self, did_seek: bool, request_id: str | None) -> Any:
        from foxglove.websocket import PlaybackState, PlaybackStatus

        head = self.playhead
        status = (
            PlaybackStatus.Ended
            if head.ended
            else PlaybackStatus.Playing
            if head.playing
            else PlaybackStatus.Paused
        )
        return PlaybackState(
            status=status,
            current_time=head.at_ms * _NS_PER_MS,
            playback_speed=head.speed,
            did_seek=did_seek,
            request_id=request_id,
        )

    # --- the player ---------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                command, arg = self.commands.get(timeout=TICK_S)
            except queue.Empty:
                command, arg = "tick", None
            try:
                self._do(command, arg)
                if command != "resend":  # those a subscribe asked for, once they are due
                    self._do("resend", None)
            except Exception as exc:  # a failed read ends no session: the next command goes on
                log.warning("foxglove replay step failed", command=command, error=str(exc))

    def _do(self, command: str, arg: Any) -> None:
        scene = self.scene
        assert scene is not None
        if command == "seek":
            time.sleep(_AFTER_ANSWER_S)
            with self.lock:
                at_ms, self._seek_to = self._seek_to, None
            if at_ms is not None:
                scene.draw_at(at_ms)
                self.server.broadcast_time(at_ms * _NS_PER_MS)
        elif command == "resend":
            for topic in self.resends.due():
                scene.resend(topic)
        elif command == "tick":
            self._tick(scene)

    def _tick(self, scene: FoxgloveScene) -> None:
        with self.lock:
            head = self.playhead
            if not head.playing:
                return
            from_ms, speed = head.at_ms, head.speed
            due_ms = int((time.monotonic() - head.wall_s) * 1000 * speed)
            step_ms = min(due_ms, int(MAX_TICK_WINDOWS * TICK_S * 1000 * speed))
            to_ms = min(self.end_ms, from_ms + max(1, step_ms))
        self._play(scene, from_ms, to_ms)
        with self.lock:
            if head.at_ms != from_ms or not head.playing:
                return  # a seek or pause came meanwhile: it decides where the playhead is
            head.at_ms = to_ms
            # What was played moves the wall clock's mark on; a playback that could not keep
            # up is behind by at most one window (it does not race to catch up later).
            head.wall_s = max(
                head.wall_s + (to_ms - from_ms) / 1000 / speed,
                time.monotonic() - MAX_TICK_WINDOWS * TICK_S,
            )
            ended = to_ms >= self.end_ms
            if ended:
                head.playing, head.ended = False, True
            state = self._state(did_seek=False, request_id=None)
        self.server.broadcast_time(to_ms * _NS_PER_MS)
        if ended:
            self.server.broadcast_playback_state(state)

    def _play(self, scene: FoxgloveScene, from_ms: int, to_ms: int) -> None:
        """[from_ms, to_ms)'s chunk writes, poses and findings (incidents, conflicts, VDA
        5050 facts), in event-time order (writes and findings first at one instant, as the
        map at that instant holds them), then the floor once."""
        history = self.sources.history
        changes = window_changes(history, from_ms, to_ms)
        found = scene.findings.play(from_ms, to_ms)
        i = k = 0
        for pose in window_poses(history, from_ms, to_ms):
            f = k
            while f < len(found) and found[f][0] <= pose.ts_ms:
                f += 1
            scene.findings.send(found[k:f])
            k = f
            j = i
            while j < len(changes) and changes[j].ts_ms <= pose.ts_ms:
                j += 1
            if j > i:
                self.sent_changes += scene.chunk_changes(_change(c) for c in changes[i:j])
                i = j
            scene.pose(pose)
        if i < len(changes):
            self.sent_changes += scene.chunk_changes(_change(c) for c in changes[i:])
        scene.findings.send(found[k:])
        scene.grid(to_ms - 1)


def _speed(requested: float, current: float, max_speed: float) -> float:
    """The playback speed a request sets, held to `max_speed` (an infinite one too); one
    that is no speed (NaN, zero or less: the protocol's float allows them) keeps
    `current`."""
    if math.isnan(requested) or requested <= 0:
        return current
    return min(requested, max_speed)


def _change(row: ChunkRow) -> ChunkChange:
    return ChunkChange(row.row, row.column, row.robot_id, row.content_hash, row.ts_ms)
