"""A time window of the history as MCAP, which Foxglove and Lichtblick replay: the map as a
`foxglove.Grid`; per robot its pose as `foxglove.PoseInFrame`, its planned path as
`foxglove.PosesInFrame`, its frame in the map as `foxglove.FrameTransform` on `/tf`, and its
battery, charging and loaded flags as a JSON channel whose JSON schema states the units; a
VDA 5050 vehicle's errors and warnings and its connection state as JSON channels too, and
the incidents (with their markers as `foxglove.SceneUpdate`) and conflicts (mcap_findings);
the operators' annotations standing as `foxglove.SceneUpdate` on `/annotations` and their
commands with the robots' answers as JSON on `/commands` (mcap_annotations). Topic names and
JSON schemas: mcap_channels; the messages: foxglove_messages (the Foxglove WebSocket server
sends the same). CSV and Parquet: table_export.

May depend on: the ports (it reads the window through the roles of `ReplaySources`)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import BinaryIO

from mapservice.adapters.foxglove_messages import (
    Floor,
    path_message,
    pose_message,
    state_doc,
    transform_message,
    window_poses,
)
from mapservice.adapters.mcap_annotations import (
    ANNOTATIONS_TOPIC,
    COMMANDS_SCHEMA_NAME,
    COMMANDS_TOPIC,
    annotation_states,
    command_messages,
    scene_update,
)
from mapservice.adapters.mcap_channels import (
    CONFLICT_SCHEMA_NAME,
    CONNECTION_SCHEMA_NAME,
    ERRORS_SCHEMA_NAME,
    INCIDENT_MARKERS_TOPIC,
    INCIDENT_SCHEMA_NAME,
    JSON_SCHEMAS,
    MAP_TOPIC,
    STATE_SCHEMA_NAME,
    TF_TOPIC,
    path_topic,
    pose_topic,
    state_topic,
)
from mapservice.adapters.mcap_findings import (
    conflict_messages,
    incident_messages,
    markers_of,
    vda_messages,
)
from mapservice.core.ports import (
    AnnotationReader,
    CommandReader,
    ConflictReader,
    IncidentReader,
    PoseRow,
    TimeTravelReader,
    VdaReader,
)
from mapservice.core.store_roles import StoreRoles


@dataclass
class McapCounts:
    grids: int = 0
    poses: int = 0
    chunk_changes: int = 0
    states: int = 0
    paths: int = 0
    vda_errors: int = 0  # messages on the errors channels (a clear is one)
    vda_connections: int = 0
    annotation_updates: int = 0  # SceneUpdates on /annotations (the start's state is one)
    commands: int = 0
    transforms: int = 0  # foxglove.FrameTransform on /tf, one with each pose
    incidents: int = 0  # messages on /incidents (a start, an end, one going on at the start)
    incident_markers: int = 0  # SceneUpdates on /incidents/markers, one per incident message
    conflicts: int = 0


class _McapOut:
    """One MCAP file with protobuf channels (Foxglove's schemas) and JSON channels (with
    their JSON schema), one channel per topic."""

    def __init__(self, out: BinaryIO):
        from mcap.writer import CompressionType, Writer

        self.writer = Writer(out, compression=CompressionType.LZ4)
        self.writer.start(profile="", library="mapservice")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}

    def _channel(self, topic: str, schema: str, register) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            if schema not in self._schemas:
                self._schemas[schema] = register()
            channel = self._channels[topic] = self.writer.register_channel(
                topic=topic,
                message_encoding="json" if schema in JSON_SCHEMAS else "protobuf",
                schema_id=self._schemas[schema],
            )
        return channel

    def protobuf(self, topic: str, message, ts_ms: int) -> None:
        from mcap_protobuf.schema import register_schema

        channel = self._channel(
            topic,
            type(message).DESCRIPTOR.full_name,
            lambda: register_schema(self.writer, type(message)),
        )
        self._add(channel, message.SerializeToString(), ts_ms)

    def json(self, topic: str, schema: str, doc: dict, ts_ms: int) -> None:
        channel = self._channel(
            topic,
            schema,
            lambda: self.writer.register_schema(
                name=schema, encoding="jsonschema", data=json.dumps(JSON_SCHEMAS[schema]).encode()
            ),
        )
        self._add(channel, json.dumps(doc, separators=(",", ":")).encode(), ts_ms)

    def _add(self, channel: int, data: bytes, ts_ms: int) -> None:
        self.writer.add_message(
            channel_id=channel,
            log_time=ts_ms * 1_000_000,
            data=data,
            publish_time=ts_ms * 1_000_000,
        )

    def finish(self) -> None:
        self.writer.finish()


# The count each side message adds to, by its JSON schema (a protobuf one's: by its topic);
# the rest are the annotations' SceneUpdates.
_COUNTED = {
    ERRORS_SCHEMA_NAME: "vda_errors",
    CONNECTION_SCHEMA_NAME: "vda_connections",
    COMMANDS_SCHEMA_NAME: "commands",
    INCIDENT_SCHEMA_NAME: "incidents",
    CONFLICT_SCHEMA_NAME: "conflicts",
    INCIDENT_MARKERS_TOPIC: "incident_markers",
}


@dataclass(frozen=True)
class ReplaySources:
    """The store's roles a replay (an export, the Foxglove server) reads: the map and poses
    (`history`), VDA 5050 facts, the annotations, the commands, the incidents and the
    conflicts."""

    history: TimeTravelReader
    vda: VdaReader
    annotations: AnnotationReader
    commands: CommandReader
    incidents: IncidentReader
    conflicts: ConflictReader

    @classmethod
    def of(cls, roles: StoreRoles) -> ReplaySources:
        return cls(
            roles.history,
            roles.vda,
            roles.annotations,
            roles.commands,
            roles.incidents,
            roles.conflicts,
        )


def _side_messages(
    sources: ReplaySources, from_ms: int, to_ms: int
) -> list[tuple[int, str, str | None, object]]:
    """Everything besides the map and poses, as (log time, topic, JSON schema name or None
    for a protobuf message, message), in time order: VDA 5050 facts, the annotations standing
    at `from_ms` and after each edit, the commands with the robots' answers, the incidents
    (those going on at `from_ms`, each start and end) and the conflicts."""
    out: list[tuple[int, str, str | None, object]] = list(vda_messages(sources.vda, from_ms, to_ms))
    incidents = incident_messages(sources.incidents, from_ms, to_ms)
    out += incidents
    out += markers_of(incidents)
    out += conflict_messages(sources.conflicts, from_ms, to_ms)
    out += [
        (t, ANNOTATIONS_TOPIC, None, scene_update(t, standing))
        for t, standing in annotation_states(sources.annotations, from_ms, to_ms)
    ]
    out += [
        (t, COMMANDS_TOPIC, COMMANDS_SCHEMA_NAME, doc)
        for t, doc in command_messages(sources.commands, from_ms, to_ms)
    ]
    return sorted(out, key=lambda m: (m[0], m[1]))


def export_mcap(
    sources: ReplaySources,
    from_ms: int,
    to_ms: int,
    out: BinaryIO,
    *,
    grid_every_ms: int = 10_000,
    page: int = 50_000,
) -> McapCounts:
    """Writes the window as MCAP: the map at `from_ms`, again after chunk changes (at most
    one grid per `grid_every_ms`, and the last state), every pose with its state (battery,
    charging, loaded), and each robot's planned path when it changes (an empty path when
    the robot drops it), VDA 5050 vehicles' errors and connection states, the annotations
    standing at `from_ms` and after each edit, the commands, the incidents and the conflicts. Returns the counts."""
    store = sources.history
    meta = store.latest_meta()
    if meta is None:
        raise ValueError("no map geometry is set yet (the 2019 meta); nothing to export")
    counts = McapCounts()
    floor = Floor(meta, store)
    floor.apply([(c.row, c.column, c.content_hash) for c in store.map_at(from_ms)])
    writer = _McapOut(out)
    paths: dict[str, tuple | None] = {}
    side = _side_messages(sources, from_ms, to_ms)
    side_next = 0

    def write_side(until_ms: int) -> None:
        """The side messages (VDA, annotations, commands, incidents, conflicts) before
        `until_ms` not yet written (log times stay in order)."""
        nonlocal side_next
        while side_next < len(side) and side[side_next][0] < until_ms:
            ts_ms, topic, schema, payload = side[side_next]
            if isinstance(payload, dict) and schema is not None:
                writer.json(topic, schema, payload, ts_ms)
            else:
                writer.protobuf(topic, payload, ts_ms)
            counted = _COUNTED.get(schema or topic, "annotation_updates")
            setattr(counts, counted, getattr(counts, counted) + 1)
            side_next += 1

    def write_grid(ts_ms: int) -> None:
        write_side(ts_ms)
        writer.protobuf(MAP_TOPIC, floor.grid(ts_ms), ts_ms)
        counts.grids += 1

    def write_pose(row: PoseRow) -> None:
        write_side(row.ts_ms)
        writer.protobuf(pose_topic(row.robot_id), pose_message(row), row.ts_ms)
        writer.protobuf(TF_TOPIC, transform_message(row), row.ts_ms)
        writer.json(state_topic(row.robot_id), STATE_SCHEMA_NAME, state_doc(row), row.ts_ms)
        counts.poses += 1
        counts.transforms += 1
        counts.states += 1
        path = tuple(row.path) if row.path else None
        if row.robot_id not in paths and path is None:
            paths[row.robot_id] = None  # no path yet: nothing to draw
        elif paths.get(row.robot_id, ()) != path:
            paths[row.robot_id] = path
            writer.protobuf(path_topic(row.robot_id), path_message(row), row.ts_ms)
            counts.paths += 1

    write_grid(from_ms)
    changes = store.chunk_events(from_ms, to_ms, limit=1_000_000)
    poses = window_poses(store, from_ms, to_ms, page)
    pending: list[tuple[int, int, str]] = []
    last_grid_ms = from_ms
    next_pose = next(poses, None)
    for change in changes + [None]:
        # Poses up to this change's time first: MCAP readers like log times in order.
        until = change.ts_ms if change is not None else to_ms
        while next_pose is not None and next_pose.ts_ms < until:
            if pending and next_pose.ts_ms - last_grid_ms >= grid_every_ms:
                floor.apply(pending)
                pending = []
                last_grid_ms = next_pose.ts_ms
                write_grid(last_grid_ms)
            write_pose(next_pose)
            next_pose = next(poses, None)
        if change is None:
            break
        pending.append((change.row, change.column, change.content_hash))
        counts.chunk_changes += 1
        if change.ts_ms - last_grid_ms >= grid_every_ms:
            floor.apply(pending)
            pending = []
            last_grid_ms = change.ts_ms
            write_grid(last_grid_ms)
    if pending:
        floor.apply(pending)
        write_grid(max(last_grid_ms, to_ms - 1))
    write_side(max(to_ms, from_ms + 1))  # the rest (the annotations at from_ms, when from == to)
    writer.finish()
    return counts
