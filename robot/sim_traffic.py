"""Giving way: a robot about to drive within `give_way_m` of another robot (closer than it
is now) waits where it stands instead, as long as it stands there for `give_way_s` at most
(less than the stuck window, so that giving way is no incident); then it drives on anyway
(two robots meeting head-on in an aisle would wait for each other for ever). So robots whose
routes cross pass one after the other, and a near miss happens only where waiting ran out.

A tick's move is judged at every second of it (the demo history steps 12 s at a time) against
where the robots moved before it in the tick were at that second, and where the others stand.
"""

from __future__ import annotations

import math

from .sim_model import Point, Robot, SimState, advance_along, evolve


class Traffic:
    """The robots' places at each second of one tick, as the tick moves them one by one."""

    def __init__(self, state: SimState) -> None:
        c = state.config
        self.on = c.give_way_m > 0
        self.steps = max(1, round(c.dt_s))
        self.clear_px = c.give_way_m / state.ros_map.resolution
        # it waits a tick only if it would then have stood for at most give_way_s
        self.max_wait_s, self.dt_s = c.give_way_s - c.dt_s, c.dt_s
        self.idle_drain = c.idle_drain_per_s * c.dt_s
        # robot id -> its places at the tick's seconds (robots not moved yet: where they are)
        self.places: dict[str, list[Point]] = {r.robot_id: [r.pos] for r in state.robots}
        self.starts = {r.robot_id: r.pos for r in state.robots}
        # robots waiting this tick for another: no one waits for them (they wait for it)
        self.waiting: set[str] = set()

    def move(self, before: Robot, after: Robot) -> Robot:
        """`after` (the robot's step), or `before` waiting a tick if that drove in the way."""
        if not self.on:
            return after
        if after.pos == before.pos:
            self.places[before.robot_id] = [after.pos]
            return evolve(after, still_s=before.still_s + self.dt_s)
        mine = self._along(before, after)
        # Only a robot that has not stood for long already waits: standing with its route
        # for the stuck window would be an incident. Nor does one arriving: it will stand
        # there anyway.
        if before.still_s <= self.max_wait_s and after.waypoints and self._in_the_way(before, mine):
            self.places[before.robot_id] = [before.pos]
            self.waiting.add(before.robot_id)
            # A robot about to leave where it stood (a charger) stays as it was, without
            # its new route.
            return evolve(
                before,
                still_s=before.still_s + self.dt_s,
                battery=max(0.0, before.battery - self.idle_drain),
            )
        self.places[before.robot_id] = mine
        return evolve(after, still_s=0.0)

    def _along(self, before: Robot, after: Robot) -> list[Point]:
        """The robot's places at the tick's seconds, driving from `before` to `after`."""
        if not before.waypoints:  # leaving: its route is new, the move is short of a tick
            return [
                (
                    before.pos[0] + (after.pos[0] - before.pos[0]) * k / self.steps,
                    before.pos[1] + (after.pos[1] - before.pos[1]) * k / self.steps,
                )
                for k in range(1, self.steps + 1)
            ]
        total = _route_length(before, after)
        return [
            advance_along(before.pos, before.yaw, before.waypoints, total * k / self.steps)[0]
            for k in range(1, self.steps + 1)
        ]

    def _in_the_way(self, robot: Robot, mine: list[Point]) -> bool:
        reach = math.dist(robot.pos, mine[-1]) + self.clear_px
        for other, theirs in self.places.items():
            if other == robot.robot_id or other in self.waiting:
                continue
            start = self.starts[other]
            now = math.dist(robot.pos, start)
            if now > reach + math.dist(start, theirs[-1]) + self.clear_px:
                continue  # too far apart to meet this tick
            for k, here in enumerate(mine):
                there = theirs[min(k, len(theirs) - 1)]
                apart = math.dist(here, there)
                if apart < self.clear_px and apart < now:
                    return True
        return False


def _route_length(before: Robot, after: Robot) -> float:
    """How far the robot drove from `before` to `after`: along the waypoints it passed."""
    passed = len(before.waypoints) - len(after.waypoints)
    points = [before.pos, *before.waypoints[:passed], after.pos]
    return sum(math.dist(a, b) for a, b in zip(points, points[1:], strict=False))
