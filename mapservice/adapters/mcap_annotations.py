"""The operators' side of a replay export: the annotations standing (points of interest and
zones) as `foxglove.SceneUpdate` messages on `/annotations`, and operators' commands with
the robots' answers as JSON on `/commands`.

Each SceneUpdate is the whole set standing from its instant on: it first deletes every
entity, then draws each annotation (a reader that seeks lands on a complete picture, and a
removal needs no entity of its own). Zones are closed lines in the map frame (keep-out red,
speed limits amber with their limit in the label, notes blue) with their name as text;
points of interest are small spheres with their name.

May depend on: the ports and the annotation and command events."""

from __future__ import annotations

from mapservice.core.annotations import (
    AnnotationRemoved,
    PointOfInterest,
    Shape,
    Zone,
)
from mapservice.core.commands import CommandAcknowledged, CommandIssued, StoredCommandEvent
from mapservice.core.ports import AnnotationReader, CommandReader

ANNOTATIONS_TOPIC = "/annotations"
COMMANDS_TOPIC = "/commands"
_MAP_FRAME = "map"
_RGBA = {
    "keep_out": (0.9, 0.1, 0.1, 1.0),
    "speed_limit": (1.0, 0.65, 0.0, 1.0),
    "note": (0.2, 0.45, 0.95, 1.0),
}
_POI_RGBA = (0.1, 0.7, 0.3, 1.0)

COMMANDS_SCHEMA_NAME = "mapservice.CommandEvent"
COMMANDS_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": COMMANDS_SCHEMA_NAME,
    "description": "An operator's command to a robot (issued) or the robot's answer (ack, "
    "outcome), at the issue time or the robot's time of its answer",
    "type": "object",
    "properties": {
        "event": {"type": "string", "enum": ["issued", "ack", "outcome"]},
        "command_id": {"type": "string", "description": "shared by a command and its answers"},
        "robot_id": {"type": "string", "description": "the robot commanded (and answering)"},
        "by": {
            "type": "string",
            "description": "who: the operator's credential name (issued) "
            "or the robot (ack, outcome)",
        },
        "kind": {
            "type": ["string", "null"],
            "enum": ["pause", "resume", "goto_poi", "cancel", None],
            "description": "what was commanded (an answer's, when its command is known)",
        },
        "status": {
            "type": "string",
            "description": "issued; ack: accepted or rejected; outcome: done, failed or cancelled",
        },
        "poi_id": {"type": ["string", "null"], "description": "a goto_poi's point of interest"},
        "x": {"type": ["number", "null"], "description": "a goto_poi's goal x (metres, map)"},
        "y": {"type": ["number", "null"], "description": "a goto_poi's goal y (metres, map)"},
        "reason": {"type": "string", "description": "why a robot rejected or failed it"},
    },
    "required": ["event", "command_id", "robot_id", "by", "kind", "status", "reason"],
}


def command_doc(stored: StoredCommandEvent, kinds: dict[str, str]) -> dict:
    """One command event as the `/commands` message; `kinds` (command id -> kind) is filled
    by issues so that later answers name what they answer."""
    e = stored.event
    if isinstance(e, CommandIssued):
        kinds[e.command_id] = e.kind
        return {
            "event": "issued",
            "command_id": e.command_id,
            "robot_id": e.robot_id,
            "by": e.issued_by,
            "kind": e.kind,
            "status": "issued",
            "poi_id": e.poi_id,
            "x": e.x,
            "y": e.y,
            "reason": "",
        }
    is_ack = isinstance(e, CommandAcknowledged)
    return {
        "event": "ack" if is_ack else "outcome",
        "command_id": e.command_id,
        "robot_id": e.robot_id,
        "by": e.robot_id,
        "kind": kinds.get(e.command_id),
        "status": e.status if isinstance(e, CommandAcknowledged) else e.outcome,
        "poi_id": None,
        "x": None,
        "y": None,
        "reason": e.reason,
    }


def command_messages(
    store: CommandReader, from_ms: int, to_ms: int, limit: int = 1_000_000
) -> list[tuple[int, dict]]:
    """The window's command events as (log time, `/commands` document), in time order."""
    kinds: dict[str, str] = {}
    return [
        (s.ts_ms, command_doc(s, kinds)) for s in store.command_events(from_ms, to_ms, limit=limit)
    ]


def annotation_states(
    store: AnnotationReader, from_ms: int, to_ms: int, limit: int = 1_000_000
) -> list[tuple[int, dict[str, Shape]]]:
    """The annotations standing at `from_ms` (left out when none stand: an empty scene is
    what a reader shows before any message), then after each instant of the window with an
    edit, as (instant, id -> annotation); edits at `from_ms` are already in the first."""
    current = {c.annotation_id: c.annotation for c in store.annotations_at(from_ms)}
    out: list[tuple[int, dict[str, Shape]]] = [(from_ms, dict(current))] if current else []
    for edit in store.annotation_edits(from_ms + 1, to_ms, limit=limit):
        ev = edit.event
        if isinstance(ev, AnnotationRemoved):
            current.pop(ev.annotation_id, None)
        else:
            current[ev.annotation_id] = ev.annotation
        if out and out[-1][0] == edit.ts_ms:
            out[-1] = (edit.ts_ms, dict(current))  # one message per instant
        else:
            out.append((edit.ts_ms, dict(current)))
    return out


def zone_label(zone: Zone) -> str:
    if zone.kind == "speed_limit" and zone.speed_limit is not None:
        unit = "%" if zone.speed_unit == "percent" else f" {zone.speed_unit}"
        return f"{zone.name} (speed limit {zone.speed_limit:g}{unit})"
    if zone.kind == "keep_out":
        return f"{zone.name} (keep out)"
    return zone.name


def scene_update(ts_ms: int, annotations: dict[str, Shape]):
    """The annotations standing as a foxglove.SceneUpdate that replaces every entity."""
    from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    update = SceneUpdate()
    deletion = update.deletions.add()
    deletion.timestamp.FromMilliseconds(ts_ms)
    deletion.type = SceneEntityDeletion.Type.ALL
    for annotation_id in sorted(annotations):
        shape = annotations[annotation_id]
        entity = update.entities.add()
        entity.timestamp.FromMilliseconds(ts_ms)
        entity.frame_id, entity.id = _MAP_FRAME, annotation_id
        entity.lifetime.SetInParent()  # zero: until deleted (present, as Foxglove's schema wants)
        for key, value in (
            ("shape", "zone" if isinstance(shape, Zone) else "poi"),
            ("kind", shape.kind),
            ("name", shape.name),
        ):
            pair = entity.metadata.add()
            pair.key, pair.value = key, value
        if isinstance(shape, Zone):
            _draw_zone(entity, shape)
        else:
            _draw_poi(entity, shape)
    return update


def paint(target, rgba: tuple[float, float, float, float]) -> None:
    """A Foxglove primitive's colour."""
    target.r, target.g, target.b, target.a = rgba


def label_at(entity, x: float, y: float, text: str, rgba) -> None:
    """A text on the entity at (x, y) of the map, facing the viewer at any zoom."""
    label = entity.texts.add()
    label.pose.position.x, label.pose.position.y, label.pose.position.z = x, y, 0.3
    label.pose.orientation.w = 1.0
    label.billboard, label.scale_invariant, label.font_size = True, True, 14.0
    label.text = text
    paint(label.color, rgba)


def _draw_zone(entity, zone: Zone) -> None:
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive

    rgba = _RGBA.get(zone.kind, _RGBA["note"])
    for ring in (zone.polygon, *zone.holes):
        line = entity.lines.add()
        line.type = LinePrimitive.Type.LINE_LOOP
        line.pose.orientation.w = 1.0
        line.thickness, line.scale_invariant = 0.05, False
        for x, y in ring:
            point = line.points.add()
            point.x, point.y = x, y
        paint(line.color, rgba)
    xs, ys = [p[0] for p in zone.polygon], [p[1] for p in zone.polygon]
    label_at(entity, sum(xs) / len(xs), sum(ys) / len(ys), zone_label(zone), rgba)


def _draw_poi(entity, poi: PointOfInterest) -> None:
    marker = entity.spheres.add()
    marker.pose.position.x, marker.pose.position.y = poi.x, poi.y
    marker.pose.orientation.w = 1.0
    marker.size.x = marker.size.y = marker.size.z = 0.3
    paint(marker.color, _POI_RGBA)
    label_at(entity, poi.x, poi.y, f"{poi.name} ({poi.kind})", _POI_RGBA)
