"""What a Foxglove client sees of the plant, on one SDK context: the floor, every robot
(pose, transform, state, planned path), each stored chunk write, the annotations and what
was found (incidents, conflicts, VDA 5050 errors: foxglove_findings.py), kept
as they were last sent so that a client subscribing later gets the current picture, and
drawn whole at an instant (the floor and robots at T, as `/api/v1/map?at=` and
`/api/v1/robots?at=` read them: snapshot plus events). Fed by the live stream
(foxglove_live.py) or a replay session's reads (foxglove_replay.py).

Not thread-safe: one thread drives a scene (its owner's worker).

May depend on: the ports (the store's time-travel and annotation reads)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from mapservice.adapters.foxglove_channels import FoxgloveChannels
from mapservice.adapters.foxglove_findings import FoxgloveFindings
from mapservice.adapters.foxglove_messages import (
    Floor,
    path_message,
    pose_message,
    state_doc,
    transform_message,
)
from mapservice.adapters.mcap_annotations import ANNOTATIONS_TOPIC, scene_update
from mapservice.adapters.mcap_channels import (
    CHUNK_CHANGE_SCHEMA_NAME,
    MAP_CHANGES_TOPIC,
    MAP_TOPIC,
    STATE_SCHEMA_NAME,
    TF_TOPIC,
    path_topic,
    pose_topic,
    state_topic,
)
from mapservice.adapters.mcap_export import ReplaySources
from mapservice.core.annotations import Shape
from mapservice.core.ports import PoseRow

# A page of robots_at: a floor of this many robots is drawn in one read.
_ROBOTS_PAGE = 10_000


@dataclass(frozen=True)
class ChunkChange:
    """One stored chunk write (a live message's or the store's `ChunkRow`)."""

    row: int
    column: int
    robot_id: str
    content_hash: str  # hex
    ts_ms: int


class FoxgloveScene:
    """The channels' current picture and how it changes."""

    def __init__(self, channels: FoxgloveChannels, sources: ReplaySources) -> None:
        self.channels, self.history, self.annotation_store = (
            channels,
            sources.history,
            sources.annotations,
        )
        # The incidents, conflicts and VDA 5050 errors (their channels declared there).
        self.findings = FoxgloveFindings(channels, sources)
        self.floor: Floor | None = None
        self.floor_ms = 0  # the instant the floor shows
        self.floor_dirty = False  # chunk writes applied since the last grid sent
        self.robots: dict[str, PoseRow] = {}
        self._paths: dict[str, tuple[tuple[float, float], ...] | None] = {}
        self.standing: dict[str, Shape] | None = None
        self.standing_ms = 0
        # The channels every picture has, advertised before their first message: a client
        # subscribes at connect and misses none of their messages (a robot's channels come
        # with the robot; a late subscriber gets its current messages again, `resend`).
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.Grid_pb2 import Grid
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
        from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        self._classes = {"pose": PoseInFrame, "path": PosesInFrame, "tf": FrameTransform}

        channels.declare_protobuf(MAP_TOPIC, Grid)
        channels.declare_protobuf(TF_TOPIC, FrameTransform)
        channels.declare_protobuf(ANNOTATIONS_TOPIC, SceneUpdate)
        channels.declare_json(MAP_CHANGES_TOPIC, CHUNK_CHANGE_SCHEMA_NAME)

    # --- the picture at an instant ------------------------------------------------------

    def declare_robots_at(self, at_ms: int) -> int:
        """Declares the channels of every robot standing at `at_ms` (each robot of the
        history up to then), sending nothing; how many robots. A server does this before its
        client connects: the SDK advertises a channel made later to a connected client before
        it records the advertisement, so a client quick to subscribe is told "unknown channel"
        (seen on a loaded machine; the API's gate then subscribes it again); channels made
        before the client connects come in its first advertisement, which its subscriptions
        cannot overtake, and need none of that."""
        count = 0
        for row in self._robots_at(at_ms):
            self._declare_robot(row.robot_id)
            count += 1
        return count

    def _robots_at(self, at_ms: int) -> Iterator[PoseRow]:
        """Every robot's pose at `at_ms` (robots_at), a page of them at a time."""
        after: str | None = None
        while True:
            page = self.history.robots_at(at_ms, after=after, limit=_ROBOTS_PAGE)
            yield from page
            if len(page) < _ROBOTS_PAGE:
                return
            after = page[-1].robot_id

    def _declare_robot(self, robot_id: str) -> None:
        self.channels.declare_protobuf(pose_topic(robot_id), self._classes["pose"])
        self.channels.declare_protobuf(path_topic(robot_id), self._classes["path"])
        self.channels.declare_json(state_topic(robot_id), STATE_SCHEMA_NAME)

    def draw_at(self, at_ms: int) -> None:
        """The floor, every robot, the annotations, the incidents going on and each VDA 5050
        vehicle's errors as they stood at `at_ms`."""
        meta = self.history.latest_meta()
        self.floor = Floor(meta, self.history) if meta is not None else None
        if self.floor is not None:
            self.floor.apply((c.row, c.column, c.content_hash) for c in self.history.map_at(at_ms))
            self.floor_ms, self.floor_dirty = at_ms, False
            self.channels.protobuf(MAP_TOPIC, self.floor.grid(at_ms), at_ms)
        self.robots, self._paths = {}, {}
        for row in self._robots_at(at_ms):
            self.pose(row, path_always=True)
        self.annotations_at(at_ms, force=True)
        self.findings.draw_at(at_ms)

    def annotations_at(self, at_ms: int, force: bool = False) -> bool:
        """Sends the annotations standing at `at_ms` if they changed (or `force`); whether
        it sent them."""
        standing = {
            c.annotation_id: c.annotation for c in self.annotation_store.annotations_at(at_ms)
        }
        if not force and standing == self.standing:
            return False
        self.standing, self.standing_ms = standing, at_ms
        self.channels.protobuf(ANNOTATIONS_TOPIC, scene_update(at_ms, standing), at_ms)
        return True

    # --- changes ------------------------------------------------------------------------

    def pose(self, row: PoseRow, path_always: bool = False) -> None:
        """A robot's pose, transform and state; its planned path when it changed (with
        `path_always`, also an unchanged one: a seek's picture is complete)."""
        self.robots[row.robot_id] = row
        self._protobuf(pose_topic(row.robot_id), "pose", lambda: pose_message(row), row.ts_ms)
        self._protobuf(TF_TOPIC, "tf", lambda: transform_message(row), row.ts_ms)
        self.channels.declare_json(state_topic(row.robot_id), STATE_SCHEMA_NAME)
        if self.channels.listened(state_topic(row.robot_id)):
            self.channels.json(
                state_topic(row.robot_id), STATE_SCHEMA_NAME, state_doc(row), row.ts_ms
            )
        path = tuple(row.path) if row.path else None
        known = row.robot_id in self._paths
        if path_always or (known and self._paths[row.robot_id] != path) or (path and not known):
            self._protobuf(path_topic(row.robot_id), "path", lambda: path_message(row), row.ts_ms)
        self._paths[row.robot_id] = path

    def _protobuf(self, topic: str, kind: str, build: Callable[[], Any], ts_ms: int) -> None:
        """build()'s message on `topic` (declared: advertised with its robot), built only
        when a client takes it: a server nobody watches spends nothing per pose."""
        self.channels.declare_protobuf(topic, self._classes[kind])
        if self.channels.listened(topic):
            self.channels.protobuf(topic, build(), ts_ms)

    def chunk_changes(self, changes: Iterable[ChunkChange]) -> int:
        """Each write on the changes channel, drawn into the floor (sent by `grid`)."""
        changes = list(changes)
        if not changes:
            return 0
        if self.floor is None:
            meta = self.history.latest_meta()
            if meta is None:
                return 0  # no geometry yet: no floor to draw into
            self.floor = Floor(meta, self.history)
        for c in changes if self.channels.listened(MAP_CHANGES_TOPIC) else ():
            self.channels.json(
                MAP_CHANGES_TOPIC,
                CHUNK_CHANGE_SCHEMA_NAME,
                {
                    "row": c.row,
                    "column": c.column,
                    "robot_id": c.robot_id,
                    "content_hash": c.content_hash,
                    "ts_ms": c.ts_ms,
                },
                c.ts_ms,
            )
        self.floor.apply((c.row, c.column, c.content_hash) for c in changes)
        self.floor_ms, self.floor_dirty = max(self.floor_ms, changes[-1].ts_ms), True
        return len(changes)

    def grid(self, ts_ms: int | None = None) -> bool:
        """Sends the floor if writes were drawn since the last one; whether it did."""
        if self.floor is None or not self.floor_dirty or not self.channels.listened(MAP_TOPIC):
            return False  # a client that subscribes later gets the floor then (`resend`)
        at = self.floor_ms if ts_ms is None else ts_ms
        self.channels.protobuf(MAP_TOPIC, self.floor.grid(at), at)
        self.floor_dirty = False
        return True

    def resend(self, topic: str) -> None:
        """The current message of `topic` again (a client just subscribed to it: the
        protocol keeps no last message for it)."""
        if self.findings.resend(topic):
            return
        if topic == MAP_TOPIC and self.floor is not None:
            self.channels.protobuf(MAP_TOPIC, self.floor.grid(self.floor_ms), self.floor_ms)
            self.floor_dirty = False
        elif topic == ANNOTATIONS_TOPIC and self.standing is not None:
            self.channels.protobuf(
                ANNOTATIONS_TOPIC, scene_update(self.standing_ms, self.standing), self.standing_ms
            )
        elif topic == TF_TOPIC:
            for row in self.robots.values():
                self.channels.protobuf(TF_TOPIC, transform_message(row), row.ts_ms)
        else:
            for row in self.robots.values():
                if topic == pose_topic(row.robot_id):
                    self.channels.protobuf(topic, pose_message(row), row.ts_ms)
                elif topic == state_topic(row.robot_id):
                    self.channels.json(topic, STATE_SCHEMA_NAME, state_doc(row), row.ts_ms)
                elif topic == path_topic(row.robot_id):
                    self.channels.protobuf(topic, path_message(row), row.ts_ms)
