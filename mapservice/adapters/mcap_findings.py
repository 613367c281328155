"""What the processors found, as Foxglove channels (the MCAP export and the Foxglove
WebSocket server send the same): incidents on `/incidents` and conflicts on `/conflicts`
(JSON, their schemas: mcap_channels), and a VDA 5050 vehicle's errors and connection
states on its own channels (`/robots/<id>/errors`, `/robots/<id>/connection`).

Each incident message has its marker on `/incidents/markers` (a `foxglove.SceneUpdate`: a
sphere at its place, red when critical, amber else, labelled with its kind and robots,
deleted at its end).

An incident is one message at its start and one at its end (an ongoing one: its start
only), each saying what was known of it then: at its start it is ongoing with no end, and
its evidence is the poses up to that instant; its kind's figure is the one last found. A
reader that starts at T (a seek, an export's start) gets the incidents going on at T.
Live, each finding the processors announce is one message (a start, an update of an
ongoing one, an end, or a retraction: the live detection dropped it).

May depend on: the ports, the incident model and the annotations' drawing helpers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mapservice.adapters.mcap_annotations import label_at, paint
from mapservice.adapters.mcap_channels import (
    CONFLICT_SCHEMA_NAME,
    CONFLICTS_TOPIC,
    CONNECTION_SCHEMA_NAME,
    ERRORS_SCHEMA_NAME,
    INCIDENT_MARKERS_TOPIC,
    INCIDENT_SCHEMA_NAME,
    INCIDENTS_TOPIC,
    MAP_FRAME,
    connection_topic,
    errors_topic,
)
from mapservice.core.incident_model import Incident, PoseRef
from mapservice.core.ports import ConflictReader, ConflictRow, IncidentReader, VdaReader

# (log time, topic, JSON schema name, document)
Message = tuple[int, str, str, dict[str, Any]]

# A vehicle's errors hold until its next state; one seen this long before a seek is shown
# at the seek (VDA 5050 vehicles send a state at least every 30 s).
ERRORS_LOOKBACK_MS = 60_000
# Rows read at once for one span (a larger span is a slower read, never a partial one:
# the readers' own limits stop a runaway).
_LIMIT = 1_000_000


def incident_doc(incident: Incident, event: str, at_ms: int) -> dict[str, Any]:
    """The incident as known at `at_ms`: ended only if it ended by then, its evidence the
    poses up to then."""
    ended = not incident.ongoing and incident.end_ms <= at_ms
    return {
        "event": event,
        "id": incident.incident_id,
        "kind": incident.kind,
        "robots": list(incident.robots),
        "start_ms": incident.start_ms,
        "end_ms": incident.end_ms if ended else None,
        "ongoing": not ended,
        "severity": incident.severity,
        "x": incident.x,
        "y": incident.y,
        "measure": incident.measure,
        "evidence": [
            {"robot_id": e.robot_id, "ts_ms": e.ts_ms, "x": e.x, "y": e.y}
            for e in incident.evidence
            if e.ts_ms <= at_ms
        ],
    }


def incident_of_live(listed: Mapping[str, Any]) -> Incident:
    """An incident of a live `incident` message (core/live_incidents.py: as the API lists it)."""
    return Incident(
        incident_id=str(listed["id"]),
        kind=str(listed["kind"]),
        robots=tuple(str(r) for r in listed["robots"]),
        start_ms=int(listed["start_ms"]),
        end_ms=int(listed["end_ms"]),
        ongoing=bool(listed["ongoing"]),
        x=float(listed["x"]),
        y=float(listed["y"]),
        severity=str(listed["severity"]),
        measure=float(listed["measure"]),
        evidence=tuple(
            PoseRef(str(e["robotId"]), int(e["ts_ms"]), float(e["x"]), float(e["y"]))
            for e in listed["evidence"]
        ),
    )


_SEVERITY_RGBA = {"critical": (0.9, 0.1, 0.1, 1.0), "warning": (1.0, 0.65, 0.0, 1.0)}


def incident_marker(doc: Mapping[str, Any], ts_ms: int) -> Any:
    """An incident message's marker (foxglove.SceneUpdate): its entity drawn, or deleted
    once it ended or was retracted."""
    from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    update = SceneUpdate()
    if doc["event"] in ("end", "retracted"):
        deletion = update.deletions.add()
        deletion.timestamp.FromMilliseconds(ts_ms)
        deletion.type, deletion.id = SceneEntityDeletion.Type.MATCHING_ID, doc["id"]
        return update
    entity = update.entities.add()
    entity.timestamp.FromMilliseconds(ts_ms)
    entity.frame_id, entity.id = MAP_FRAME, doc["id"]
    entity.lifetime.SetInParent()  # zero: until deleted (present, as Foxglove's schema wants)
    rgba = _SEVERITY_RGBA.get(doc["severity"], _SEVERITY_RGBA["warning"])
    sphere = entity.spheres.add()
    sphere.pose.position.x, sphere.pose.position.y = doc["x"], doc["y"]
    sphere.pose.orientation.w = 1.0
    sphere.size.x = sphere.size.y = sphere.size.z = 0.6
    paint(sphere.color, (*rgba[:3], 0.6))
    label_at(entity, doc["x"], doc["y"], f"{doc['kind']} ({', '.join(doc['robots'])})", rgba)
    return update


def markers_of(messages: list[Message]) -> list[tuple[int, str, None, Any]]:
    """The markers of the incident messages among `messages` (log time, topic, no JSON
    schema: protobuf, SceneUpdate)."""
    return [
        (t, INCIDENT_MARKERS_TOPIC, None, incident_marker(doc, t))
        for t, topic, _, doc in messages
        if topic == INCIDENTS_TOPIC
    ]


def conflict_doc(conflict: ConflictRow) -> dict[str, Any]:
    return {
        "row": conflict.row,
        "column": conflict.column,
        "ts_ms": conflict.ts_ms,
        "robot_b": conflict.robot_b,
        "robot_a": conflict.robot_a,
        "ts_a_ms": conflict.ts_a_ms,
    }


def _incident(at_ms: int, incident: Incident, event: str) -> Message:
    return (at_ms, INCIDENTS_TOPIC, INCIDENT_SCHEMA_NAME, incident_doc(incident, event, at_ms))


def incidents_at(store: IncidentReader, at_ms: int) -> list[Message]:
    """The incidents going on at `at_ms` (begun at or before it, not ended before it; one
    ending at it as its end), each as known then."""
    return [
        _incident(at_ms, i, "end" if not i.ongoing and i.end_ms <= at_ms else "ongoing")
        for i in store.incidents(at_ms, at_ms + 1, limit=_LIMIT)
        if i.start_ms <= at_ms
    ]


def incident_messages(
    store: IncidentReader, from_ms: int, to_ms: int, going_on: bool = True
) -> list[Message]:
    """[from_ms, to_ms)'s incident messages in time order: with `going_on`, those going on
    at `from_ms` (begun before it) first; each start and each end in the span."""
    out: list[Message] = []
    for i in store.incidents(from_ms, to_ms, limit=_LIMIT):
        if i.start_ms >= from_ms:
            instant = not i.ongoing and i.end_ms == i.start_ms  # over as it began: one message
            out.append(_incident(i.start_ms, i, "end" if instant else "start"))
        elif going_on:
            out.append(_incident(from_ms, i, "ongoing"))
        if not i.ongoing and from_ms <= i.end_ms < to_ms and i.end_ms > i.start_ms:
            out.append(_incident(i.end_ms, i, "end"))
    return sorted(out, key=lambda m: (m[0], m[3]["event"] != "ongoing"))


def conflict_messages(store: ConflictReader, from_ms: int, to_ms: int) -> list[Message]:
    return [
        (c.ts_ms, CONFLICTS_TOPIC, CONFLICT_SCHEMA_NAME, conflict_doc(c))
        for c in store.conflicts(from_ms, to_ms, limit=_LIMIT)
    ]


def _errors_doc(errors: list[dict[str, str]]) -> dict[str, Any]:
    return {
        "count": len(errors),
        "fatal": sum(e["level"] != "WARNING" for e in errors),
        "errors": errors,
    }


def _error_instants(facts: Any) -> dict[int, list[dict[str, str]]]:
    """A vehicle's error instants (and clears: no errors) -> the errors then."""
    instants: dict[int, list[dict[str, str]]] = {t: [] for t in facts.error_clears}
    for e in facts.errors:
        instants.setdefault(e.ts_ms, []).append(
            {"level": e.level, "type": e.type, "description": e.description}
        )
    return instants


def vda_messages(store: VdaReader, from_ms: int, to_ms: int) -> list[Message]:
    """The span's VDA 5050 errors (one message per error instant and per clear) and
    connection states, in time order."""
    out: list[Message] = []
    for robot_id, facts in store.vda_fleet_facts(from_ms, to_ms, limit=_LIMIT).items():
        out += [
            (t, errors_topic(robot_id), ERRORS_SCHEMA_NAME, _errors_doc(errs))
            for t, errs in _error_instants(facts).items()
        ]
        out += [
            (
                c.ts_ms,
                connection_topic(robot_id),
                CONNECTION_SCHEMA_NAME,
                {"state": c.state, "online": c.state == "ONLINE", "sent_ms": c.sent_ms},
            )
            for c in facts.connections
        ]
    return sorted(out, key=lambda m: (m[0], m[1]))


def vda_errors_at(store: VdaReader, at_ms: int) -> list[Message]:
    """Each vehicle's errors standing at `at_ms` (its latest error instant or clear within
    `ERRORS_LOOKBACK_MS`), at that instant."""
    out: list[Message] = []
    facts_by_robot = store.vda_fleet_facts(at_ms - ERRORS_LOOKBACK_MS, at_ms + 1, limit=_LIMIT)
    for robot_id, facts in facts_by_robot.items():
        instants = _error_instants(facts)
        if instants:
            last = max(instants)
            out.append(
                (last, errors_topic(robot_id), ERRORS_SCHEMA_NAME, _errors_doc(instants[last]))
            )
    return sorted(out, key=lambda m: (m[0], m[1]))
