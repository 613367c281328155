"""Operators' commands to robots, and the robots' answers, as immutable events.

An operator (through the API) issues a command to one robot: pause, resume, go to a point
of interest, or cancel its goal. The robot acknowledges it at once (accepted, or rejected
with a reason) and later reports its outcome (done, failed, cancelled). All three are
events on the command topic, keyed by the robot, stored as history (they expire with the
retention, as poses do).

The wire forms are JSON: `command_message` is what a robot receives on its own command
topic (`iot/robots/<robotId>/commands`), `response_message` what it publishes on
`iot/robots/<robotId>/command-events` (the gateway's ingest/command_responses.py reads it).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from typing import Any

import msgspec

COMMAND_KINDS = ("pause", "resume", "goto_poi", "cancel")
ACK_STATUSES = ("accepted", "rejected")
OUTCOMES = ("done", "failed", "cancelled")
MAX_REASON_CHARS = 500
COMMAND_ID = re.compile(r"[A-Za-z0-9_.:-]{1,100}")


class CommandIssued(msgspec.Struct, frozen=True, gc=False, tag="command.issued", array_like=True):
    """An operator told a robot to do something. `issued_by` is the credential's name
    (never a secret); a goto_poi carries the point's id and its position as it stood when
    the command was issued (the robot needs no other read to obey)."""

    command_id: str
    robot_id: str
    kind: str  # COMMAND_KINDS
    issued_by: str
    issued_at_ms: int
    poi_id: str | None = None
    x: float | None = None
    y: float | None = None
    heading: float | None = None


class CommandAcknowledged(
    msgspec.Struct, frozen=True, gc=False, tag="command.ack", array_like=True
):
    """The robot took the command (accepted) or refused it (rejected, with its reason)."""

    command_id: str
    robot_id: str
    status: str  # ACK_STATUSES
    reason: str = ""


class CommandFinished(
    msgspec.Struct, frozen=True, gc=False, tag="command.outcome", array_like=True
):
    """How an accepted command ended: done, failed (with a reason) or cancelled."""

    command_id: str
    robot_id: str
    outcome: str  # OUTCOMES
    reason: str = ""


CommandResponse = CommandAcknowledged | CommandFinished
CommandEvent = CommandIssued | CommandAcknowledged | CommandFinished
COMMAND_EVENTS = (CommandIssued, CommandAcknowledged, CommandFinished)


class StoredCommandEvent(msgspec.Struct, frozen=True, gc=False):
    """One stored command event: when (the issue time, or the robot's time of its answer)."""

    ts_ms: int
    event_id: str
    event: CommandEvent


class CommandError(ValueError):
    """A command that cannot be issued; the message says what to fix."""


def check_command_id(command_id: str) -> None:
    if not COMMAND_ID.fullmatch(command_id):
        raise CommandError(
            f"a command id is 1 to 100 letters, digits or '-_.:', not {command_id[:120]!r}"
        )


def check_issue(command: CommandIssued) -> None:
    """Raises CommandError saying what is wrong; returns for a command a robot can obey."""
    check_command_id(command.command_id)
    if command.kind not in COMMAND_KINDS:
        raise CommandError(
            f"a command's kind is one of {', '.join(COMMAND_KINDS)}, not {command.kind[:40]!r}"
        )
    if command.kind == "goto_poi":
        if not command.poi_id or command.x is None or command.y is None:
            raise CommandError("a goto_poi command names its point of interest (poi_id)")
        if not (math.isfinite(command.x) and math.isfinite(command.y)):
            raise CommandError("a goto_poi target must be finite metres")
    elif command.poi_id is not None:
        raise CommandError(f"only goto_poi names a point of interest, not {command.kind}")


# A VDA 5050 vehicle takes these commands as instant actions (ingest/vda_commands.py).
VDA_ACTION_TYPES = {"pause": "startPause", "resume": "stopPause", "cancel": "cancelOrder"}


def vda_refusal(kind: str) -> str | None:
    """Why a command of this kind cannot go to a VDA 5050 vehicle (None: it can)."""
    if kind in VDA_ACTION_TYPES:
        return None
    return (
        f"a VDA 5050 vehicle takes {', '.join(VDA_ACTION_TYPES)} (as instant actions); "
        f"{kind} would need an order, which mapservice does not send: send the vehicle "
        "an order from its master control"
    )


# --- the wire: what a robot receives and what it answers --------------------------------


def command_message(command: CommandIssued) -> dict[str, Any]:
    """The JSON a robot receives on its command topic."""
    doc: dict[str, Any] = {
        "commandId": command.command_id,
        "robotId": command.robot_id,
        "kind": command.kind,
        "issuedBy": command.issued_by,
        "issuedAt": command.issued_at_ms,
    }
    if command.kind == "goto_poi":
        doc["poiId"] = command.poi_id
        doc["target"] = {"x": command.x, "y": command.y, "heading": command.heading}
    return doc


def parse_command_message(data: bytes) -> CommandIssued:
    """A command as a robot reads it off its topic; ValueError when it is not one."""
    doc = msgspec.json.decode(data)
    if not isinstance(doc, dict):
        raise ValueError("a command is a JSON object")
    target = doc.get("target") or {}
    heading = target.get("heading")
    return CommandIssued(
        command_id=str(doc["commandId"]),
        robot_id=str(doc["robotId"]),
        kind=str(doc["kind"]),
        issued_by=str(doc.get("issuedBy", "")),
        issued_at_ms=int(doc.get("issuedAt", 0)),
        poi_id=doc.get("poiId"),
        x=float(target["x"]) if "x" in target else None,
        y=float(target["y"]) if "y" in target else None,
        heading=float(heading) if heading is not None else None,
    )


def response_message(response: CommandResponse, timestamp: str) -> dict[str, Any]:
    """The JSON a robot publishes for an ack or an outcome (the robot side's encoder)."""
    doc: dict[str, Any] = {
        "robotId": response.robot_id,
        "commandId": response.command_id,
        "timestamp": timestamp,
        "reason": response.reason,
    }
    if isinstance(response, CommandAcknowledged):
        doc.update(type="ack", status=response.status)
    else:
        doc.update(type="outcome", outcome=response.outcome)
    return doc


# --- the history: each command with its answers ----------------------------------------


class CommandRecord(msgspec.Struct):
    """A command with the robot's latest ack and outcome up to the read's end (None: none yet)."""

    ts_ms: int
    command: CommandIssued
    ack: tuple[int, CommandAcknowledged] | None = None
    outcome: tuple[int, CommandFinished] | None = None


def command_records(events: Iterable[StoredCommandEvent]) -> list[CommandRecord]:
    """The commands among `events` with their answers among them, in issue order. An
    answer counts only from the robot the command was sent to (the gateway refuses the
    others; this holds even for events that reached the log some other way)."""
    records: dict[str, CommandRecord] = {}
    ordered = sorted(events, key=lambda e: (e.ts_ms, e.event_id))
    for stored in ordered:
        ev = stored.event
        if isinstance(ev, CommandIssued):
            records.setdefault(ev.command_id, CommandRecord(stored.ts_ms, ev))
    for stored in ordered:
        ev = stored.event
        if isinstance(ev, CommandIssued):
            continue
        record = records.get(ev.command_id)
        if record is None or record.command.robot_id != ev.robot_id:
            continue
        if isinstance(ev, CommandAcknowledged):
            record.ack = (stored.ts_ms, ev)
        else:
            record.outcome = (stored.ts_ms, ev)
    return sorted(records.values(), key=lambda r: (r.ts_ms, r.command.command_id))
