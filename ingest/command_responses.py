"""A robot's answers to its commands, read off `iot/robots/<robotId>/command-events`.

Each is an ack (accepted or rejected) or an outcome (done, failed, cancelled) of a command
that robot was sent: anything malformed, about another robot or about a command the
gateway never delivered to it becomes a dead letter with its reason.
"""

from __future__ import annotations

from collections.abc import Callable

import msgspec

from mapservice.core.commands import (
    ACK_STATUSES,
    COMMAND_ID,
    MAX_REASON_CHARS,
    OUTCOMES,
    CommandAcknowledged,
    CommandFinished,
    CommandResponse,
)
from mapservice.core.wire2019 import Limits, Reason, Rejection, check_time


class ResponseMessage(msgspec.Struct, forbid_unknown_fields=False):
    """What a robot publishes on its command-events topic (ISO 8601 `timestamp`, as its
    poses): {"type": "ack", "status": "accepted"|"rejected"} or {"type": "outcome",
    "outcome": "done"|"failed"|"cancelled"}, with an optional `reason`."""

    robotId: str
    commandId: str
    type: str
    timestamp: str
    status: str | None = None
    outcome: str | None = None
    reason: str = ""


_response_decoder = msgspec.json.Decoder(ResponseMessage)


def decode_response(
    data: bytes,
    topic_robot_id: str,
    receive_ms: int,
    limits: Limits,
    command_robot: Callable[[str], str | None],
) -> tuple[int, CommandResponse] | Rejection:
    """A robot's ack or outcome and its time, or why not. `command_robot(id)` is the robot
    the command was sent to (None: no such command is known): a robot answers only its
    own commands."""
    if len(data) > limits.max_message_bytes:
        return Rejection(Reason.OVERSIZED, f"{len(data)} bytes; at most {limits.max_message_bytes}")
    try:
        msg = _response_decoder.decode(data)
    except msgspec.ValidationError as exc:
        reason = Reason.MISSING_FIELD if "missing required field" in str(exc) else Reason.WRONG_TYPE
        return Rejection(
            reason,
            f"{exc}; a command response is {{robotId, commandId, type: "
            "ack|outcome, timestamp, status or outcome, reason}",
        )
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        return Rejection(Reason.NOT_JSON, f"payload is not JSON: {exc}")
    except RecursionError:
        return Rejection(Reason.TOO_DEEP, "JSON nested too deeply to decode")
    if msg.robotId != topic_robot_id:
        return Rejection(
            Reason.ROBOT_ID_MISMATCH,
            f"topic names robot {topic_robot_id[:80]!r} but the payload says {msg.robotId[:80]!r}",
        )
    if not COMMAND_ID.fullmatch(msg.commandId):
        return Rejection(
            Reason.WRONG_TYPE, f"commandId {msg.commandId[:120]!r} is not a command id"
        )
    if len(msg.reason) > MAX_REASON_CHARS:
        return Rejection(
            Reason.OUT_OF_RANGE,
            f"reason has {len(msg.reason)} characters; at most {MAX_REASON_CHARS}",
        )
    response: CommandResponse
    if msg.type == "ack":
        if msg.status not in ACK_STATUSES:
            return Rejection(
                Reason.BAD_COMMAND_RESPONSE,
                f"an ack's status is one of "
                f"{', '.join(ACK_STATUSES)}, not {str(msg.status)[:40]!r}",
            )
        response = CommandAcknowledged(msg.commandId, topic_robot_id, msg.status, msg.reason)
    elif msg.type == "outcome":
        if msg.outcome not in OUTCOMES:
            return Rejection(
                Reason.BAD_COMMAND_RESPONSE,
                f"an outcome is one of {', '.join(OUTCOMES)}, not {str(msg.outcome)[:40]!r}",
            )
        response = CommandFinished(msg.commandId, topic_robot_id, msg.outcome, msg.reason)
    else:
        return Rejection(
            Reason.BAD_COMMAND_RESPONSE, f"type is 'ack' or 'outcome', not {msg.type[:40]!r}"
        )
    ts = check_time(msg.timestamp, receive_ms, limits)
    if isinstance(ts, Rejection):
        return ts
    owner = command_robot(msg.commandId)
    if owner is None:
        return Rejection(
            Reason.UNKNOWN_COMMAND,
            f"no command {msg.commandId!r} was sent (or it "
            "is older than the gateway remembers); answer only commands received "
            "on your command topic",
        )
    if owner != topic_robot_id:
        return Rejection(
            Reason.NOT_ITS_COMMAND,
            f"command {msg.commandId!r} was sent to another "
            f"robot, not {topic_robot_id[:80]!r}; a robot answers only its own commands",
        )
    return ts, response
