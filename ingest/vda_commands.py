"""Operators' commands to VDA 5050 vehicles, and the vehicles' answers to them.

A command to a robot whose id is a vehicle's (`vehicle_of`) goes out as an
`instantActions` message on `<interface>/<major>/<manufacturer>/<serialNumber>/instantActions`
(pause -> startPause, resume -> stopPause, cancel -> cancelOrder; the action's id is the
command's id), in the protocol version the vehicle last spoke to this gateway (its latest
state, connection or factsheet), 2.0.0 while it has said nothing yet. A vehicle cannot go
to a point of interest without an order, which the service does not compose: goto_poi is
refused (the API answers 422; the relay never sends it).

The vehicle answers in its `state`: each `actionStates` entry naming a command's id
becomes that command's ack (RUNNING, FINISHED: accepted) and outcome (FINISHED: done,
FAILED: failed with the vehicle's resultDescription), each at most once per command.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from datetime import UTC, datetime
from typing import Any

from cachetools import LRUCache

from mapservice.core.commands import (
    MAX_REASON_CHARS,
    CommandAcknowledged,
    CommandFinished,
    CommandIssued,
    CommandResponse,
)
from mapservice.core.commands import (
    VDA_ACTION_TYPES as ACTION_TYPES,
)
from mapservice.core.commands import (
    vda_refusal as refusal,
)
from mapservice.core.vda_ids import vehicle_of

DEFAULT_VERSION = "2.0.0"  # a vehicle not heard from yet: the oldest version taken
MAX_VEHICLES = 100_000  # vehicles whose version and last headerId are held
MAX_ANSWERS = 400_000  # (command, answer) pairs remembered so each is sent once


class VdaCommandRefused(ValueError):
    """A command a VDA 5050 vehicle cannot be sent; the message says why."""


def instant_actions_message(
    command: CommandIssued,
    manufacturer: str,
    serial_number: str,
    version: str,
    header_id: int,
    timestamp: str,
) -> dict[str, Any]:
    """The `instantActions` message carrying one command, in the schema of `version`
    (2.0.x names the list `instantActions`, 2.1 and later `actions`; 3.0 allows only the
    blocking type NONE for an instant action)."""
    why = refusal(command.kind)
    if why is not None:
        raise VdaCommandRefused(why)
    action = {
        "actionId": command.command_id,
        "actionType": ACTION_TYPES[command.kind],
        "blockingType": "NONE" if version.startswith("3.") else "HARD",
    }
    return {
        "headerId": header_id,
        "timestamp": timestamp,
        "version": version,
        "manufacturer": manufacturer,
        "serialNumber": serial_number,
        "instantActions" if version.startswith("2.0.") else "actions": [action],
    }


def vda_timestamp(ms: int) -> str:
    """ISO 8601 in UTC with its `Z` (the schemas' date-time; vehicles refuse a time without
    a zone)."""
    return datetime.fromtimestamp(ms / 1000, UTC).isoformat(timespec="milliseconds")[:-6] + "Z"


class VdaCommands:
    """Per vehicle: the version it speaks and the headerId of its instant actions; per
    command: which answers were already made. Thread-safe (the relay's thread sends,
    paho's thread reads states)."""

    def __init__(
        self,
        interface: str,
        command_robot: Callable[[str], str | None],
        wall_s: Callable[[], float] = time.time,
    ) -> None:
        self.interface = interface
        self.command_robot = command_robot
        self.wall_s = wall_s
        self.versions: LRUCache[str, str] = LRUCache(MAX_VEHICLES)
        self._header_ids: LRUCache[str, int] = LRUCache(MAX_VEHICLES)
        self._answered: LRUCache[tuple[str, str], bool] = LRUCache(MAX_ANSWERS)
        self._lock = threading.Lock()

    def heard(self, robot_id: str, version: str) -> None:
        """The vehicle spoke `version` (its latest state, connection or factsheet)."""
        with self._lock:
            self.versions[robot_id] = version

    def is_vehicle(self, robot_id: str) -> bool:
        return bool(self.interface) and vehicle_of(robot_id) is not None

    def _next_header_id(self, robot_id: str) -> int:
        # Counted from the wall clock's seconds, so the ids keep increasing across a
        # gateway's restart unless it sent one vehicle more than one message a second.
        with self._lock:
            header_id = max(self._header_ids.get(robot_id, -1) + 1, int(self.wall_s()))
            self._header_ids[robot_id] = header_id
            return header_id

    def delivery(self, command: CommandIssued, now_ms: int) -> tuple[str, dict[str, Any]]:
        """The MQTT topic and message of a command to a vehicle; VdaCommandRefused if the
        vehicle cannot take it."""
        names = vehicle_of(command.robot_id)
        if names is None:
            raise VdaCommandRefused(f"{command.robot_id!r} is not a VDA 5050 vehicle's robot id")
        why = refusal(command.kind)
        if why is not None:
            raise VdaCommandRefused(why)
        with self._lock:
            version = self.versions.get(command.robot_id, DEFAULT_VERSION)
        manufacturer, serial = names
        message = instant_actions_message(
            command,
            manufacturer,
            serial,
            version,
            self._next_header_id(command.robot_id),
            vda_timestamp(now_ms),
        )
        topic = f"{self.interface}/v{version.split('.')[0]}/{manufacturer}/{serial}/instantActions"
        return topic, message

    def answers(self, robot_id: str, action_states: Iterable[Any]) -> list[CommandResponse]:
        """The command events a vehicle's `actionStates` make, each once: only for
        commands sent to this vehicle (other actions are its orders' or another master
        control's)."""
        made: list[CommandResponse] = []
        for state in action_states:
            if not isinstance(state, dict):
                continue
            command_id, status = state.get("actionId"), state.get("actionStatus")
            if not isinstance(command_id, str) or self.command_robot(command_id) != robot_id:
                continue
            found: list[CommandResponse] = []
            if status in ("RUNNING", "FINISHED"):
                found.append(CommandAcknowledged(command_id, robot_id, "accepted"))
            if status == "FINISHED":
                found.append(CommandFinished(command_id, robot_id, "done"))
            elif status == "FAILED":
                reason = str(state.get("resultDescription") or "the vehicle reports FAILED")
                found.append(
                    CommandFinished(command_id, robot_id, "failed", reason[:MAX_REASON_CHARS])
                )
            with self._lock:
                for response in found:
                    key = (
                        command_id,
                        "ack" if isinstance(response, CommandAcknowledged) else "outcome",
                    )
                    if key not in self._answered:
                        self._answered[key] = True
                        made.append(response)
        return made
