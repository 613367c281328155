"""Giving way: a robot about to drive within `give_way_m` of another robot (closer than it
is now) waits where it stands instead, as long as it stands there for `give_way_s` at most
(less than the stuck window, so that giving way is no incident). When waiting runs out (the
other stands on its route, or waits for it in turn) it drives around: a route planned on the
grid with the cells within `give_way_m` of the robots near it blocked, kept to its side as
any route. Only where there is no way around (the other stands on its goal, an aisle too
narrow for two) does it drive on anyway, and a near miss happens. So robots whose routes
cross pass one after the other, and a robot standing in the way is passed at a distance.

A tick's move is judged at every second of it (the demo history steps 12 s at a time) against
where the robots moved before it in the tick were at that second, and where the others stand.
"""

from __future__ import annotations

import math

import numpy as np

from .planning import PlanGrid, dilate, plan
from .sim_lanes import keep_to_side
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
        self.grid, self.side_px = state.grid, c.keep_side_m / state.ros_map.resolution
        # the cells around a robot a detour keeps off: within give_way_m of its cell
        self.detour_radius = math.ceil(
            c.give_way_m / (state.grid.cell_px * state.ros_map.resolution)
        )
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
        blocked = bool(after.waypoints) and self._in_the_way(before, mine)
        if blocked and before.still_s > self.max_wait_s:
            around = self._around(before, after)
            if around is not None:
                after, mine = around
        elif blocked:
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

    def _around(self, before: Robot, after: Robot) -> tuple[Robot, list[Point]] | None:
        """`after` driven as far on a route around the robots near `before` instead, and its
        places this tick; None when there is no such route or it ends within the tick."""
        g = self.grid
        here, goal = g.cell_at(*before.pos), g.cell_at(*after.waypoints[-1])
        others = np.zeros(g.shape, dtype=bool)
        for other, theirs in self.places.items():
            if other != before.robot_id:
                others[g.cell_at(*theirs[-1])] = others[g.cell_at(*self.starts[other])] = True
        keep_off = dilate(others, self.detour_radius)
        keep_off[here] = keep_off[goal] = False
        grid = PlanGrid(g.cell_px, g.ok & ~keep_off)
        cells = plan(grid, here, goal)
        if cells is None:
            return None
        route = (before.pos, *keep_to_side(grid, cells, self.side_px))
        pos, yaw, passed = advance_along(
            before.pos, before.yaw, route, _route_length(before, after)
        )
        if passed >= len(route):
            return None
        moved = evolve(after, pos=pos, yaw=yaw, waypoints=route[passed:])
        return moved, self._along(evolve(before, waypoints=route), moved)

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
