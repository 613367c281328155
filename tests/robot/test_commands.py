"""Simulated robots obey operators' commands (robot/commands.py around sim.step): a paused
robot reports the same position from the next tick on while the others drive, resume lets
it go on, goto_poi drives it to the point and reports done, cancel drops the goal (a goto
in progress ends cancelled), every command is acked at once, a redelivered command is
acted on once, and the answers are the JSON the gateway reads."""

from __future__ import annotations

import math
from types import SimpleNamespace

import msgspec

from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.commands import CommandIssued, command_message
from mapservice.robot.commands import CommandInbox, SimCommands, command_topic, response_topic
from mapservice.robot.sim import SimConfig, new_state, step
from tests.fixtures.paths import MAPS

T0 = 1_795_255_200_000


def fleet(robots: int = 3):
    state = new_state(
        load_ros_map(MAPS / "warehouse.yaml"),
        robots,
        seed=5,
        t_ms=T0,
        config=SimConfig(change_every_s=0, dwell_s=1.0),
    )
    inbox = CommandInbox(r.robot_id for r in state.robots)
    return state, inbox, SimCommands(inbox)


def deliver(inbox: CommandInbox, command: CommandIssued) -> None:
    msg = SimpleNamespace(
        topic=command_topic(command.robot_id), payload=msgspec.json.encode(command_message(command))
    )
    inbox.on_message(None, None, msg)


def tick(state, commands: SimCommands):
    before = commands.before_step(state)
    return commands.after_step(before, *step(before))


def answers(commands: SimCommands) -> list[dict]:
    out = commands.drain()
    for o in out:
        assert o.topic == response_topic(o.robot_id)
    return [msgspec.json.decode(o.payload) for o in out]


def command(cid: str, robot: str, kind: str, **extra) -> CommandIssued:
    return CommandIssued(cid, robot, kind, "operator:test", T0, **extra)


def test_pause_holds_the_robot_where_it_is_and_resume_lets_it_go() -> None:
    state, inbox, commands = fleet()
    for _ in range(15):  # under way
        state, out = tick(state, commands)
    target = state.robots[0].robot_id
    deliver(inbox, command("c-1", target, "pause"))
    state, out = tick(state, commands)
    said = answers(commands)
    assert [(a["type"], a.get("status") or a.get("outcome")) for a in said] == [
        ("ack", "accepted"),
        ("outcome", "done"),
    ]
    assert said[0]["robotId"] == target and said[0]["commandId"] == "c-1" and said[0]["timestamp"]
    held = {p.robot_id: (p.x, p.y) for p in out.poses}[target]
    others_moved = 0
    for _ in range(10):
        before = {p.robot_id: (p.x, p.y) for p in out.poses}
        state, out = tick(state, commands)
        now = {p.robot_id: (p.x, p.y) for p in out.poses}
        assert now[target] == held  # the same position at every later tick
        assert {p.robot_id: p.t_ms for p in out.poses}[target] == state.t_ms  # still reporting
        others_moved += sum(now[r] != before[r] for r in now if r != target)
    assert others_moved > 0
    deliver(inbox, command("c-1", target, "pause"))  # redelivered: acted on once
    state, out = tick(state, commands)
    assert answers(commands) == []
    deliver(inbox, command("c-2", target, "resume"))
    moved = False
    for _ in range(15):
        state, out = tick(state, commands)
        moved |= {p.robot_id: (p.x, p.y) for p in out.poses}[target] != held
    assert moved
    assert [a.get("status") or a.get("outcome") for a in answers(commands)] == ["accepted", "done"]
    deliver(inbox, command("c-3", target, "resume"))  # not paused: rejected, saying why
    state, out = tick(state, commands)
    (rejected,) = answers(commands)
    assert rejected["status"] == "rejected" and "not paused" in rejected["reason"]


def test_goto_poi_drives_to_the_point_and_cancel_drops_a_goal() -> None:
    state, inbox, commands = fleet(2)
    robot = state.robots[1]
    # A point another robot's station is at: drivable, somewhere else on the floor.
    from mapservice.robot.sim import to_metres

    x, y = to_metres(state, state.grid.centre_px(state.stations[3]))
    deliver(inbox, command("g-1", robot.robot_id, "goto_poi", poi_id="dock", x=x, y=y))
    done_at = None
    for n in range(400):
        state, out = tick(state, commands)
        said = answers(commands)
        if n == 0:
            assert said == [
                {
                    "robotId": robot.robot_id,
                    "commandId": "g-1",
                    "timestamp": said[0]["timestamp"],
                    "reason": "",
                    "type": "ack",
                    "status": "accepted",
                }
            ]
        elif said:
            assert [(a["type"], a["outcome"]) for a in said] == [("outcome", "done")]
            done_at = {p.robot_id: (p.x, p.y) for p in out.poses}[robot.robot_id]
            break
    assert done_at is not None and math.dist(done_at, (x, y)) < 1.0
    far = max(
        state.stations,
        key=lambda c: math.dist(state.grid.centre_px(c), state.grid.centre_px(state.stations[3])),
    )
    fx, fy = to_metres(state, state.grid.centre_px(far))
    deliver(inbox, command("g-2", robot.robot_id, "goto_poi", poi_id="far-dock", x=fx, y=fy))
    state, out = tick(state, commands)
    deliver(inbox, command("k-1", robot.robot_id, "cancel"))
    state, out = tick(state, commands)
    said = answers(commands)
    assert [(a["commandId"], a["type"], a.get("status") or a.get("outcome")) for a in said] == [
        ("g-2", "ack", "accepted"),
        ("k-1", "ack", "accepted"),
        ("g-2", "outcome", "cancelled"),
        ("k-1", "outcome", "done"),
    ]
    # A point off the floor cannot be reached: rejected at once, saying why.
    deliver(inbox, command("g-3", robot.robot_id, "goto_poi", poi_id="far", x=1e5, y=1e5))
    state, out = tick(state, commands)
    (said,) = answers(commands)
    assert said["status"] == "rejected" and "no drivable route" in said["reason"]


def test_commands_for_other_robots_or_unreadable_are_ignored() -> None:
    state, inbox, commands = fleet(1)
    deliver(inbox, command("x-1", "someone-else", "pause"))
    inbox.on_message(None, None, SimpleNamespace(topic="t", payload=b"{not json"))
    tick(state, commands)
    assert answers(commands) == [] and not commands.paused


def test_a_paused_robots_route_is_planned_again_when_the_floor_changes() -> None:
    """A pallet put across a held robot's route while it is paused: its route is planned
    on the new floor, so on resume it does not drive through the pallet."""
    from mapservice.adapters.ros_map import drivable
    from mapservice.robot.floor_changes import _occupied_value
    from mapservice.robot.planning import path_is_clear
    from mapservice.robot.sim import StepOut, _with_pixels

    state, inbox, commands = fleet(3)
    for _ in range(8):
        state, _out = tick(state, commands)
    robot = max(state.robots, key=lambda r: len(r.waypoints))
    assert len(robot.waypoints) >= 3, "a robot with a route of several stretches"
    deliver(inbox, command("p-1", robot.robot_id, "pause"))
    state, _out = tick(state, commands)
    held = next(r for r in state.robots if r.robot_id == robot.robot_id)
    (ax, ay), (bx, by) = held.waypoints[1], held.waypoints[2]  # beyond the stretch driven next
    col, row = int((ax + bx) / 2), int((ay + by) / 2)
    pixels = state.ros_map.pixels.copy()
    pixels[row - 8 : row + 8, col - 8 : col + 8] = _occupied_value(state.ros_map)
    changed = _with_pixels(state, pixels)
    assert not path_is_clear([held.pos, *held.waypoints], changed.drivable)
    after, _ = commands.after_step(state, changed, StepOut())
    moved = next(r for r in after.robots if r.robot_id == robot.robot_id)
    assert moved.pos == held.pos
    assert path_is_clear([moved.pos, *moved.waypoints], drivable(after.ros_map))
