"""The channels of an MCAP export, as a reader (Foxglove, Lichtblick, a script) finds them:
topic names, the map's frame, and the JSON schemas of the JSON channels (the robot state with
its units, a VDA 5050 vehicle's errors and connection state, the commands).

Data and naming only (mcap_export.py writes the file)."""

from __future__ import annotations

from mapservice.adapters.mcap_annotations import COMMANDS_SCHEMA, COMMANDS_SCHEMA_NAME

MAP_TOPIC = "/map"
MAP_FRAME = "map"


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
# Every JSON channel's schema by name: a channel whose schema is here is JSON, else protobuf.
JSON_SCHEMAS = {
    STATE_SCHEMA_NAME: STATE_SCHEMA,
    ERRORS_SCHEMA_NAME: ERRORS_SCHEMA,
    CONNECTION_SCHEMA_NAME: CONNECTION_SCHEMA,
    COMMANDS_SCHEMA_NAME: COMMANDS_SCHEMA,
}


def battery_percent(level: float | None) -> float | None:
    """The reported battery in %, judged from the level alone (the replay UI judges by the
    robot's highest level instead, replay-ui/src/lib/battery.ts: a percent robot's 5.0 is
    5 % there, 100 % here)."""
    if level is None or level != level:
        return None
    pct = level * 100 if level <= 1 else level * 20 if level <= 5 else level
    return round(min(100.0, max(0.0, pct)), 1)
