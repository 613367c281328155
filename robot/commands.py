"""Robots obey operators' commands: pause, resume, go to a point of interest, cancel.

A robot reads its commands on its own topic (`iot/robots/<robotId>/commands`, which the
broker lets only it read), acknowledges each at once and reports its outcome on
`iot/robots/<robotId>/command-events` (mapservice/core/commands.py has both JSON forms).
`CommandInbox` is the part every robot shares: the subscription, commands taken once by
id, the answers' messages. `SimCommands` applies them to the simulator between its ticks
without the simulator knowing (robot/sim.py stays a pure stepper): a paused robot is
held where it was before the tick (and keeps reporting there), a goto plans a route to
the point of interest on the simulator's planning grid, a cancel drops the goal.
"""

from __future__ import annotations

import queue
import time
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, replace

import msgspec
import paho.mqtt.client as mqtt
import structlog

from mapservice.core.commands import (
    CommandAcknowledged,
    CommandFinished,
    CommandIssued,
    CommandResponse,
    parse_command_message,
    response_message,
)
from mapservice.core.wire2019 import format_timestamp

from .chunks import metres_to_pixel
from .connection import RobotClients, subscribe_always
from .planning import plan, simplify
from .sim import PoseOut, Robot, SimState, StepOut

log = structlog.get_logger(__name__)

ROBOT_TOPIC_ROOT = "iot/robots/"  # MAPSERVICE_ROBOT_TOPIC_ROOT's default
REMEMBERED_IDS = 10_000  # command ids a robot remembers, to act on a redelivery once


def command_topic(robot_id: str, root: str = ROBOT_TOPIC_ROOT) -> str:
    return f"{root.rstrip('/')}/{robot_id}/commands"


def response_topic(robot_id: str, root: str = ROBOT_TOPIC_ROOT) -> str:
    return f"{root.rstrip('/')}/{robot_id}/command-events"


@dataclass(frozen=True)
class Outgoing:
    robot_id: str
    topic: str
    payload: bytes


class CommandInbox:
    """Commands received on paho's threads, taken by the robot's own loop; each command id
    once (QoS 1 and several gateways may deliver one twice)."""

    def __init__(self, robot_ids: Iterable[str], root: str = ROBOT_TOPIC_ROOT) -> None:
        self.robot_ids = set(robot_ids)
        self.root = root
        self._queue: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._seen: OrderedDict[str, None] = OrderedDict()

    def on_message(self, _client: mqtt.Client, _userdata: object, msg: mqtt.MQTTMessage) -> None:
        self._queue.put(msg.payload)

    def attach(self, client: mqtt.Client, robot_ids: Iterable[str]) -> None:
        """Subscribes `client` to these robots' command topics, now and on each reconnect."""
        client.on_message = self.on_message
        subscribe_always(client, [(command_topic(r, self.root), 1) for r in robot_ids])

    def attach_fleet(self, clients: RobotClients) -> None:
        """Each robot's own connection reads its commands; a shared anonymous one, all of them."""
        for robot_id, client in clients.clients.items():
            self.attach(client, [robot_id] if robot_id is not None else sorted(self.robot_ids))

    def take(self) -> list[CommandIssued]:
        """The new commands received since the last call, in arrival order."""
        out: list[CommandIssued] = []
        while True:
            try:
                data = self._queue.get_nowait()
            except queue.Empty:
                return out
            try:
                command = parse_command_message(data)
            except (msgspec.DecodeError, ValueError, KeyError, TypeError) as exc:
                log.warning("command not understood; ignored", error=str(exc)[:200])
                continue
            if command.robot_id not in self.robot_ids or command.command_id in self._seen:
                continue
            self._seen[command.command_id] = None
            while len(self._seen) > REMEMBERED_IDS:
                self._seen.popitem(last=False)
            out.append(command)

    def answer(self, response: CommandResponse) -> Outgoing:
        """The message of an ack or outcome, stamped now."""
        ts = format_timestamp(time.time_ns() // 1_000_000)
        return Outgoing(
            response.robot_id,
            response_topic(response.robot_id, self.root),
            msgspec.json.encode(response_message(response, ts)),
        )


def ack(command: CommandIssued, reason: str = "") -> CommandAcknowledged:
    return CommandAcknowledged(
        command.command_id, command.robot_id, "rejected" if reason else "accepted", reason
    )


def finished(command: CommandIssued, outcome: str, reason: str = "") -> CommandFinished:
    return CommandFinished(command.command_id, command.robot_id, outcome, reason)


def refusals(inbox: CommandInbox, reason: str) -> list[Outgoing]:
    """Rejections of every new command, for a robot that cannot obey them."""
    return [inbox.answer(ack(command, reason)) for command in inbox.take()]


class SimCommands:
    """The simulated fleet's commands, applied around each `sim.step`:
    `state = before_step(state)`, then `after_step(before, *step(state))`."""

    GOTO_TASK = "goto_poi"  # the task of a robot driving to an operator's point

    def __init__(self, inbox: CommandInbox) -> None:
        self.inbox = inbox
        self.paused: set[str] = set()
        self.goals: dict[str, CommandIssued] = {}  # robot -> its goto in progress
        self.outgoing: list[Outgoing] = []
        self.last_pose: dict[str, PoseOut] = {}  # what each robot reported last

    def _say(self, *responses: CommandResponse) -> None:
        self.outgoing.extend(self.inbox.answer(r) for r in responses)

    def drain(self) -> list[Outgoing]:
        out, self.outgoing = self.outgoing, []
        return out

    def before_step(self, state: SimState) -> SimState:
        """Applies the commands received since the last tick; acks each at once."""
        robots = {r.robot_id: r for r in state.robots}
        for command in self.inbox.take():
            robot = robots.get(command.robot_id)
            if robot is None:
                self._say(ack(command, "this simulator runs no such robot"))
                continue
            robots[robot.robot_id] = self._apply(state, robot, command)
        return replace(state, robots=tuple(robots[r.robot_id] for r in state.robots))

    def _apply(self, state: SimState, robot: Robot, command: CommandIssued) -> Robot:
        rid, kind = robot.robot_id, command.kind
        if kind == "pause":
            self.paused.add(rid)
            self._say(ack(command), finished(command, "done"))
        elif kind == "resume":
            if rid not in self.paused:
                self._say(ack(command, "the robot is not paused"))
                return robot
            self.paused.discard(rid)
            self._say(ack(command), finished(command, "done"))
        elif kind == "cancel":
            self._say(ack(command))
            robot = self._drop_goal(state, robot, "cancelled by an operator")
            self._say(finished(command, "done"))
        elif kind == "goto_poi":
            route = self._route(state, robot, command)
            if route is None:
                self._say(ack(command, "no drivable route to the point of interest"))
                return robot
            robot = self._drop_goal(state, robot, "replaced by another goto")
            self.goals[rid] = command
            self._say(ack(command))
            return replace(
                robot, task=self.GOTO_TASK, target=-1, waypoints=route, wait_s=0.0, charging=False
            )
        else:
            self._say(ack(command, f"unknown command kind {kind[:40]!r}"))
        return robot

    def _drop_goal(self, state: SimState, robot: Robot, why: str) -> Robot:
        """The robot stops where its current stretch ends and chooses its next task from
        there after a dwell; an operator's goto in progress ends cancelled."""
        goal = self.goals.pop(robot.robot_id, None)
        if goal is not None:
            self._say(finished(goal, "cancelled", why))
        return replace(
            robot,
            waypoints=robot.waypoints[:1],
            task="idle",
            wait_s=state.config.dwell_s,
            charging=False,
        )

    def _route(
        self, state: SimState, robot: Robot, command: CommandIssued
    ) -> tuple[tuple[float, float], ...] | None:
        if command.x is None or command.y is None:
            return None
        col, row = metres_to_pixel(command.x, command.y, state.meta)
        rows, cols = state.drivable.shape
        if not (0 <= row < rows and 0 <= col < cols):
            return None
        return self._plan(state, robot, (col + 0.5, row + 0.5))

    @staticmethod
    def _plan(
        state: SimState, robot: Robot, goal: tuple[float, float]
    ) -> tuple[tuple[float, float], ...] | None:
        """Waypoints from the robot's next waypoint (or its place) to `goal` (an image
        point) on the simulator's planning grid as it is now; None when none reach it."""
        grid = state.grid
        start_pt = robot.waypoints[0] if robot.waypoints else robot.pos
        cells = plan(grid, grid.cell_at(*start_pt), grid.cell_at(*goal))
        if cells is None:
            return None
        tail = tuple(grid.centre_px(c) for c in simplify(cells))
        return ((robot.waypoints[0],) + tail[1:]) if robot.waypoints else tail

    def _still_held(self, before: SimState, after: SimState, robot: Robot) -> Robot:
        """A held robot as before the tick; if the floor changed meanwhile, with its route
        planned again on the new floor (the simulator replanned only the moved copy)."""
        if after.grid is before.grid or not robot.waypoints:
            return robot
        route = self._plan(after, robot, robot.waypoints[-1])
        return replace(robot, waypoints=route if route is not None else robot.waypoints[:1])

    def after_step(
        self, before: SimState, after: SimState, out: StepOut
    ) -> tuple[SimState, StepOut]:
        """Holds the paused robots where they were before the tick (each reports its last
        pose again, at the tick's time) and reports the gotos that arrived or were given up."""
        # A robot paused before its first report is held from its first reported pose on.
        held = {
            r.robot_id: r
            for r in before.robots
            if r.robot_id in self.paused and r.robot_id in self.last_pose
        }
        robots = []
        for robot in after.robots:
            rid = robot.robot_id
            if rid in held:
                robots.append(self._still_held(before, after, held[rid]))
                continue
            goal = self.goals.get(rid)
            if goal is not None and robot.task != self.GOTO_TASK:
                # The simulator replanned it away (its route got blocked for good).
                del self.goals[rid]
                self._say(finished(goal, "failed", "the route to the point was blocked"))
            elif goal is not None and not robot.waypoints:
                del self.goals[rid]
                self._say(finished(goal, "done"))
                robot = replace(robot, task="dwell", wait_s=after.config.dwell_s)
            robots.append(robot)
        poses = []
        for pose in out.poses:
            last = self.last_pose.get(pose.robot_id)
            if pose.robot_id in held and last is not None:  # last is set for every held robot
                pose = replace(last, t_ms=pose.t_ms)
            self.last_pose[pose.robot_id] = pose
            poses.append(pose)
        return (
            replace(after, robots=tuple(robots)),
            StepOut(poses=poses, chunks=out.chunks, notes=out.notes),
        )
