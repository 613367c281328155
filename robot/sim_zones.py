"""Operators' zones applied to the simulation: from the moment the robots learn a zone they
plan around keep-out zones and drive slower in speed zones.

On a change of the zones the planning grid is rebuilt with the keep-out pixels blocked
(`robot/zones.py`) and the route cache emptied, and every robot checks where it stands:

- a robot whose body overlaps a keep-out zone (its planning cell is blocked: inside, or
  closer than its radius) leaves by the shortest way out over the floor, to the nearest
  cell it may plan through, then chooses its next job. Stopping there instead would leave
  it inside the zone, a violation for as long as the zone stands; leaving takes a second
  or two. A robot with no way out at all (the zone covers every cell it can reach) stops
  and says so;
- a robot whose route crosses a blocked cell plans again from where it stands; with no
  route to its goal around the zones, it stops on its cell and chooses another job.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mapservice.adapters.costmap_filters import grid_of
from mapservice.core.annotations import Zone

from .planning import Cell, PlanGrid, grid_for, plan, route_clear, simplify
from .sim_model import Point, Robot, SimConfig, SimState, to_metres
from .zones import NO_ZONES, FloorZones, blocked_grid, floor_zones


def plan_grids(
    free: np.ndarray, zones: FloorZones, resolution: float, config: SimConfig
) -> tuple[PlanGrid, PlanGrid | None]:
    """(the grid robots plan on, the floor's own grid or None when they are the same)."""
    floor = grid_for(free, resolution, config.cell_m, config.robot_radius_m)
    if zones.keep_out is None:
        return floor, None
    return blocked_grid(
        free, zones.keep_out, resolution, config.cell_m, config.robot_radius_m
    ), floor


def speed_at(state: SimState, pos: Point) -> float:
    """The robot's speed where it stands: its top speed, or a speed zone's lower limit."""
    top = state.config.speed_m_s
    limits = state.zones.speed_m_s
    if limits is None:
        return top
    row, col = int(pos[1]), int(pos[0])
    if 0 <= row < limits.shape[0] and 0 <= col < limits.shape[1]:
        return min(top, float(limits[row, col]))
    return top


def with_zones(state: SimState, zones: Sequence[tuple[str, Zone]]) -> tuple[SimState, list[str]]:
    """The state with these zones (all that stand now, by id) in force, and what robots
    did about them (human-readable notes)."""
    grid = grid_of(state.meta)
    fz = (
        floor_zones(zones, grid, state.config.speed_m_s) if grid is not None and zones else NO_ZONES
    )
    planned, floor = plan_grids(state.drivable, fz, state.ros_map.resolution, state.config)
    state = replace(state, zones=fz, grid=planned, floor_grid=floor)
    state.routes.clear()  # routes planned around other zones, or through the new ones
    robots, notes = [], []
    for robot in state.robots:
        robot, note = _respect(state, robot)
        robots.append(robot)
        if note:
            notes.append(note)
    return replace(state, robots=tuple(robots)), notes


def _sign(n: int) -> int:
    return (n > 0) - (n < 0)


def route_cells(grid: PlanGrid, points: Sequence[Point]) -> list[Cell]:
    """The cells a robot's route passes, from the cell it stands on: its waypoints are the
    ends of straight or diagonal runs of cells (`simplify`), walked here cell by cell."""
    cells = [grid.cell_at(*points[0])]
    for p in points[1:]:
        r, c = grid.cell_at(*p)
        while cells[-1] != (r, c):
            lr, lc = cells[-1]
            cells.append((lr + _sign(r - lr), lc + _sign(c - lc)))
    return cells


def way_out(floor: PlanGrid, planned: PlanGrid, start: Cell) -> list[Cell] | None:
    """The shortest 4-connected run of floor cells from `start` to a cell robots may plan
    through on `planned`, both included; None when there is none (breadth-first)."""
    came: dict[Cell, Cell | None] = {start: None}
    frontier = [start]
    for cell in frontier:  # grows while walked: a FIFO queue
        if planned.is_ok(cell):
            path = [cell]
            while (prev := came[path[-1]]) is not None:
                path.append(prev)
            return path[::-1]
        r, c = cell
        for nxt in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            if nxt not in came and floor.is_ok(nxt):
                came[nxt] = cell
                frontier.append(nxt)
    return None


def _respect(state: SimState, robot: Robot) -> tuple[Robot, str | None]:
    g = state.grid
    here = g.cell_at(*robot.pos)
    x, y = to_metres(state, robot.pos)
    if not g.is_ok(here):
        out = way_out(state.floor, g, here)
        if out is None:
            return (
                replace(
                    robot, waypoints=(), task="idle", wait_s=state.config.dwell_s, charging=False
                ),
                f"{robot.robot_id} stands in a keep-out zone at ({x:.1f}, {y:.1f}) m with "
                "no way out over the floor: it stops there",
            )
        metres = (len(out) - 1) * g.cell_px * state.ros_map.resolution
        return (
            replace(
                robot,
                waypoints=tuple(g.centre_px(c) for c in simplify(out)),
                task="leave_zone",
                charging=False,
            ),
            f"{robot.robot_id} leaves a keep-out zone at ({x:.1f}, {y:.1f}) m, "
            f"{metres:.1f} m to its edge",
        )
    if not robot.waypoints or route_clear(g, route_cells(g, (robot.pos, *robot.waypoints))):
        return robot, None
    cells = plan(g, here, g.cell_at(*robot.waypoints[-1]))
    if cells is None:
        return (
            replace(robot, waypoints=(g.centre_px(here),), task="leave_zone"),
            f"{robot.robot_id}'s goal is cut off by a keep-out zone: it chooses another job",
        )
    return replace(robot, waypoints=tuple(g.centre_px(c) for c in simplify(cells))), None
