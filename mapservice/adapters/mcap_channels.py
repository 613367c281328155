"""The Foxglove channels, as a reader (Foxglove, Lichtblick, a script) finds them in an MCAP
export and on the Foxglove WebSocket server alike: topic names, the map's and the robots'
frames, and the JSON schemas of the JSON channels (the robot state with its units, a chunk
change, a VDA 5050 vehicle's errors and connection state, the commands, an incident, a
conflict).

Data and naming only (foxglove_messages.py and mcap_findings.py build the messages,
mcap_export.py writes the file, foxglove_live.py and foxglove_replay.py serve them)."""

from __future__ import annotations

from mapservice.adapters.mcap_annotations import COMMANDS_SCHEMA, COMMANDS_SCHEMA_NAME
from mapservice.core.incident_model import KINDS, SEVERITIES

MAP_TOPIC = "/map"
MAP_FRAME = "map"
# Every robot's frame in the map (foxglove.FrameTransform), as ROS names its transforms.
TF_TOPIC = "/tf"
# Each stored chunk write, one message each (JSON): the floor's grid is sent at most so often,
# this says which writes it holds, none skipped.
MAP_CHANGES_TOPIC = "/map/changes"


def robot_frame(robot_id: str) -> str:
    return f"{robot_id}/base_link"


def pose_topic(robot_id: str) -> str:
    return f"/robots/{robot_id}/pose"


def state_topic(robot_id: str) -> str:
    return f"/robots/{robot_id}/state"


def path_topic(robot_id: str) -> str:
    return f"/robots/{robot_id}/planned_path"


def errors_topic(robot_id: str) -> str:
    return f"/robots/{robot_id}/errors"


def connection_topic(robot_id: str) -> str:
    return f"/robots/{robot_id}/connection"


STATE_SCHEMA_NAME = "mapservice.RobotState"
# The state channel's JSON schema (JSON Schema draft 2020-12, as Foxglove reads it).
STATE_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": STATE_SCHEMA_NAME,
    "description": "A robot's reported state with each pose",
    "type": "object",
    "properties": {
        "battery_level": {
            "type": ["number", "null"],
            "description": "battery as the robot reported it (a 0-1 fraction, "
            "0-5 V-like scale or %: see battery_percent)",
        },
        "battery_percent": {
            "type": ["number", "null"],
            "minimum": 0,
            "maximum": 100,
            "description": "battery in % (unit: %): level <= 1 times 100, "
            "<= 5 times 20, else as reported; clamped to 0-100",
        },
        "charging": {
            "type": ["boolean", "string", "null"],
            "description": "on a charger (a 2019 robot may send a word)",
        },
        "loaded": {
            "type": ["boolean", "string", "null"],
            "description": "carrying a load (a 2019 robot may send a word)",
        },
    },
    "required": ["battery_level", "battery_percent", "charging", "loaded"],
}


CHUNK_CHANGE_SCHEMA_NAME = "mapservice.ChunkChange"
CHUNK_CHANGE_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": CHUNK_CHANGE_SCHEMA_NAME,
    "description": "One stored write of one chunk of the floor (its pixels: "
    "GET /api/v1/chunks/contents/{content_hash})",
    "type": "object",
    "properties": {
        "row": {"type": "integer", "minimum": 0},
        "column": {"type": "integer", "minimum": 0},
        "robot_id": {"type": "string", "description": "who wrote it"},
        "content_hash": {"type": "string", "description": "the chunk's content, hex"},
        "ts_ms": {"type": "integer", "description": "event time, ms since the epoch"},
    },
    "required": ["row", "column", "robot_id", "content_hash", "ts_ms"],
}

ERRORS_SCHEMA_NAME = "mapservice.VdaErrors"
# A VDA 5050 vehicle's active errors and warnings, sent with each state that has some and
# with the first state without (an empty list): the latest message is what is active.
ERRORS_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": ERRORS_SCHEMA_NAME,
    "description": "A VDA 5050 vehicle's active errors and warnings (state.errors) from this "
    "instant until the next message",
    "type": "object",
    "properties": {
        "count": {"type": "integer", "minimum": 0, "description": "number of active errors"},
        "fatal": {"type": "integer", "minimum": 0, "description": "those not WARNING"},
        "errors": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "level": {
                        "type": "string",
                        "description": "WARNING or FATAL (3.0: also URGENT, CRITICAL)",
                    },
                    "type": {"type": "string", "description": "the vehicle's errorType"},
                    "description": {
                        "type": "string",
                        "description": "the vehicle's errorDescription",
                    },
                },
                "required": ["level", "type", "description"],
            },
        },
    },
    "required": ["count", "fatal", "errors"],
}

CONNECTION_SCHEMA_NAME = "mapservice.VdaConnection"
CONNECTION_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": CONNECTION_SCHEMA_NAME,
    "description": "A VDA 5050 vehicle's connection state from this instant on (log time: "
    "the message's timestamp; for CONNECTIONBROKEN, the broker's last will, "
    "when the gateway received it)",
    "type": "object",
    "properties": {
        "state": {"type": "string", "enum": ["ONLINE", "OFFLINE", "CONNECTIONBROKEN"]},
        "online": {"type": "boolean", "description": "state is ONLINE"},
        "sent_ms": {
            "type": "integer",
            "description": "the message's own timestamp, ms since "
            "the epoch (the last will's: connect time)",
        },
    },
    "required": ["state", "online", "sent_ms"],
}
INCIDENTS_TOPIC = "/incidents"
# Each incident going on as a marker at its place (foxglove.SceneUpdate), gone at its end.
INCIDENT_MARKERS_TOPIC = "/incidents/markers"
CONFLICTS_TOPIC = "/conflicts"

# What one incident message says happened (`ongoing`: it was going on when the reader's
# span began).
INCIDENT_EVENTS = ("start", "ongoing", "update", "end", "retracted")

INCIDENT_SCHEMA_NAME = "mapservice.Incident"
INCIDENT_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": INCIDENT_SCHEMA_NAME,
    "description": "An incident as known at the message's time: its start, an update while "
    "it goes on, its end, or its retraction (as GET /api/v1/incidents lists it)",
    "type": "object",
    "properties": {
        "event": {"type": "string", "enum": list(INCIDENT_EVENTS)},
        "id": {"type": "string", "description": "the incident's id (its messages share it)"},
        "kind": {"type": "string", "enum": list(KINDS)},
        "robots": {"type": "array", "items": {"type": "string"}},
        "start_ms": {"type": "integer", "description": "when it began, ms since the epoch"},
        "end_ms": {
            "type": ["integer", "null"],
            "description": "when it ended (null while it goes on), ms since the epoch",
        },
        "ongoing": {"type": "boolean"},
        "severity": {"type": "string", "enum": list(SEVERITIES)},
        "x": {"type": "number", "description": "where (metres, map frame)"},
        "y": {"type": "number", "description": "where (metres, map frame)"},
        "measure": {
            "type": "number",
            "description": "the kind's figure as last found: metres (near_miss), seconds "
            "(stuck, offline, zone_violation, vda_error, command_failed), % (battery_low), "
            "chunk writes (conflict)",
        },
        "evidence": {
            "type": "array",
            "description": "the stored poses that made it, up to the message's time",
            "items": {
                "type": "object",
                "properties": {
                    "robot_id": {"type": "string"},
                    "ts_ms": {"type": "integer"},
                    "x": {"type": "number"},
                    "y": {"type": "number"},
                },
                "required": ["robot_id", "ts_ms", "x", "y"],
            },
        },
    },
    "required": [
        "event",
        "id",
        "kind",
        "robots",
        "start_ms",
        "end_ms",
        "ongoing",
        "severity",
        "x",
        "y",
        "measure",
        "evidence",
    ],
}

CONFLICT_SCHEMA_NAME = "mapservice.Conflict"
CONFLICT_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": CONFLICT_SCHEMA_NAME,
    "description": "Two robots wrote different contents to one chunk within the conflict "
    "window, at the later write's time (both writes: GET /api/v1/chunks/history)",
    "type": "object",
    "properties": {
        "row": {"type": "integer", "minimum": 0},
        "column": {"type": "integer", "minimum": 0},
        "ts_ms": {"type": "integer", "description": "the later write's event time"},
        "robot_b": {"type": "string", "description": "who wrote the later write"},
        "robot_a": {"type": "string", "description": "who wrote the earlier one"},
        "ts_a_ms": {"type": "integer", "description": "the earlier write's event time"},
    },
    "required": ["row", "column", "ts_ms", "robot_b", "robot_a", "ts_a_ms"],
}

# Every JSON channel's schema by name: a channel whose schema is here is JSON, else protobuf.
JSON_SCHEMAS = {
    STATE_SCHEMA_NAME: STATE_SCHEMA,
    CHUNK_CHANGE_SCHEMA_NAME: CHUNK_CHANGE_SCHEMA,
    ERRORS_SCHEMA_NAME: ERRORS_SCHEMA,
    CONNECTION_SCHEMA_NAME: CONNECTION_SCHEMA,
    COMMANDS_SCHEMA_NAME: COMMANDS_SCHEMA,
    INCIDENT_SCHEMA_NAME: INCIDENT_SCHEMA,
    CONFLICT_SCHEMA_NAME: CONFLICT_SCHEMA,
}


def battery_percent(level: float | None) -> float | None:
    """The reported battery in %, judged from the level alone (the replay UI judges by the
    robot's highest level instead, replay-ui/src/lib/battery.ts: a percent robot's 5.0 is
    5 % there, 100 % here)."""
    if level is None or level != level:
        return None
    pct = level * 100 if level <= 1 else level * 20 if level <= 5 else level
    return round(min(100.0, max(0.0, pct)), 1)
