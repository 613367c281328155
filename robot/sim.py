"""A simulated shift on a real map, as a pure step function over a state.

`new_state(map, robots, seed)` places stations and robots; `step(state)` advances one tick
and returns the next state and what the robots would publish during it (poses with their
planned path, chunks of map changes). Nothing here touches a clock, a socket or a global
random generator: tests drive it for thousands of steps without a broker, and the runner
(`robot/simrun.py`) only encodes and publishes the outputs.

Robots cycle pick station -> drop station (loaded) -> next job, go to a charger below
`low_battery`, and never leave the inflated free space of the planning grid. Now and
then the floor changes (a pallet appears or is taken away, a door closes or opens); the
change is published as the chunks it touched, by the robot nearest to it
(`robot/floor_changes.py`). Operators' zones (`with_zones`, `robot/sim_zones.py`) block
keep-out areas on the planning grid and slow robots in speed zones.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np

from mapservice.adapters.ros_map import RosMap, drivable, meta_for

from .floor_changes import _protected, _with_pixels, change_map, replan_blocked
from .planning import Cell, PlanGrid, grid_for, largest_component, plan_cell_sizes
from .sim_incidents import charge_below, first_due, network, next_charge_level, stalled
from .sim_model import (
    MAX_CACHED_ROUTES,
    ChunkOut,
    MapChange,
    Point,
    PoseOut,
    Robot,
    RouteEntry,
    SimConfig,
    SimState,
    StepOut,
    advance_along,
    evolve,
    route_to,
    sim_robot_id,
    to_metres,
)
from .sim_traffic import Traffic
from .sim_zones import speed_at, with_zones
from .zones import FloorZones

# The names other modules and tests know the simulator by, wherever they now live.
__all__ = [
    "MAX_CACHED_ROUTES",
    "ChunkOut",
    "FloorZones",
    "MapChange",
    "Point",
    "PoseOut",
    "Robot",
    "RouteEntry",
    "SimConfig",
    "SimState",
    "StepOut",
    "_protected",
    "_route",
    "_with_pixels",
    "advance_along",
    "capacity",
    "new_state",
    "sim_robot_id",
    "step",
    "to_metres",
    "with_zones",
]
_route = route_to
RESERVE_BATTERY = 2.0  # %


# --- set-up ------------------------------------------------------------------------------


def _rng(seed: int, tick: int, salt: str = "") -> random.Random:
    return random.Random(f"{seed}:{tick}:{salt}")


def new_state(
    ros_map: RosMap,
    robots: int,
    *,
    seed: int = 7,
    t_ms: int = 0,
    config: SimConfig = SimConfig(),
    prefix: str = "sim",
    chunk_width: int = 100,
    chunk_height: int = 100,
) -> SimState:
    free = drivable(ros_map)
    config, grid, cells = _plan_grid(free, ros_map.resolution, config, robots)
    rng = _rng(seed, -1, "setup")
    picked = _spaced(cells, config.stations + config.chargers, config, rng)
    stations, chargers = tuple(picked[: config.stations]), tuple(picked[config.stations :])
    fleet = []
    for i, cell in enumerate(rng.sample(cells, min(robots, capacity(len(cells))))):
        fleet.append(
            Robot(
                sim_robot_id(prefix, i),
                grid.centre_px(cell),
                rng.uniform(-math.pi, math.pi),
                battery=round(rng.uniform(40, 100), 1),
            )
        )
    due = _rng(seed, -1, "incidents")
    fleet = [first_due(config, robot, due, t_ms) for robot in fleet]
    return SimState(
        ros_map,
        meta_for(ros_map, chunk_width, chunk_height),
        config,
        grid,
        free,
        stations,
        chargers,
        tuple(fleet),
        t_ms,
        seed,
        next_change_ms=t_ms + int(config.change_every_s * 1000),
    )


def _spaced(cells: list[Cell], n: int, config: SimConfig, rng: random.Random) -> list[Cell]:
    """`n` of the cells at random, at least `station_spacing_m` apart where the floor has
    room (two stations side by side would have their robots pass within a hand's width)."""
    picked = rng.sample(cells, n)
    if config.station_spacing_m <= 0:
        return picked
    apart = config.station_spacing_m / config.cell_m
    spaced: list[Cell] = []
    for cell in [*picked, *rng.sample(cells, min(len(cells), 50 * n))]:
        if all(math.dist(cell, other) >= apart for other in spaced):
            spaced.append(cell)
            if len(spaced) == n:
                return spaced
    return picked


def capacity(reachable_cells: int) -> int:
    """How many robots a connected free area of that many planning cells hosts: each
    starts on a cell of its own and keeps room to move (a quarter of the cells)."""
    return max(1, reachable_cells // 4)


def _plan_grid(
    free: np.ndarray, resolution: float, config: SimConfig, robots: int
) -> tuple[SimConfig, PlanGrid, list[Cell]]:
    """The coarsest planning grid (see `plan_cell_sizes`) whose largest connected free area
    holds the stations, chargers and the robots; else the one holding the most. The chosen
    cell size goes into the config so that map changes re-plan on the same grid."""
    needed = config.stations + config.chargers + 1
    best: tuple[SimConfig, PlanGrid, list[Cell]] | None = None
    for cell_px in plan_cell_sizes(resolution, config.cell_m, config.robot_radius_m):
        cfg = replace(config, cell_m=cell_px * resolution)
        grid = grid_for(free, resolution, cfg.cell_m, cfg.robot_radius_m)
        cells = list(zip(*(a.tolist() for a in np.nonzero(largest_component(grid.ok)))))
        if best is None or len(cells) > len(best[2]):
            best = (cfg, grid, cells)
        if len(cells) >= needed and capacity(len(cells)) >= robots:
            return cfg, grid, cells
    assert best is not None
    if len(best[2]) < needed:
        raise ValueError(
            f"the map has too little free space for the simulation: its largest connected "
            f"free area holds {len(best[2])} planning cells of {best[0].cell_m:.2f} m for a "
            f"{config.robot_radius_m} m robot, {needed} are needed (stations, chargers, a "
            "robot); use a map with more free space"
        )
    return best


def _advance(robot: Robot, distance_px: float, battery: float) -> Robot:
    """The robot driven `distance_px` along its waypoints, its battery then at `battery`."""
    pos, yaw, passed = advance_along(robot.pos, robot.yaw, robot.waypoints, distance_px)
    return evolve(robot, pos=pos, waypoints=robot.waypoints[passed:], yaw=yaw, battery=battery)


# --- behaviour ---------------------------------------------------------------------------


def _next_task(state: SimState, robot: Robot, rng: random.Random) -> Robot:
    """Picks what to do next and plans the route; stays put if nothing is reachable."""
    at_chargers, at_stations = _taken(state, robot)
    if robot.battery < charge_below(state.config, robot) and robot.task != "to_charger":
        options = [
            ("to_charger", i, c) for i, c in enumerate(state.chargers) if i not in at_chargers
        ]
    elif robot.loaded:
        options = [
            ("to_drop", i, c)
            for i, c in enumerate(state.stations)
            if i != robot.target and i not in at_stations
        ]
    else:
        options = [
            ("to_pick", i, c)
            for i, c in enumerate(state.stations)
            if i != robot.target and i not in at_stations
        ]
    rng.shuffle(options)
    if robot.task == "to_charger" or (options and options[0][0] == "to_charger"):
        here = robot.pos
        options.sort(key=lambda o: math.dist(here, state.grid.centre_px(o[2])))
    for task, index, cell in options[:3]:
        route = _route(state, robot, cell)
        if route is not None:
            return evolve(robot, task=task, target=index, waypoints=route)
    return evolve(robot, task="idle", wait_s=state.config.dwell_s)


def _taken(state: SimState, robot: Robot) -> tuple[set[int], set[int]]:
    """The chargers and stations other robots drive to or stand at: a robot picks another
    (two robots sharing a station would pass within a hand's width there all shift)."""
    chargers, stations = set(), set()
    for other in state.robots:
        if other.robot_id == robot.robot_id or other.target < 0:
            continue
        if other.task in ("to_charger", "charging"):
            chargers.add(other.target)
        elif other.task in ("to_pick", "to_drop", "dwell"):
            stations.add(other.target)
    return chargers, stations


def _arrive(state: SimState, robot: Robot) -> Robot:
    c = state.config
    if robot.task == "to_charger":
        return evolve(robot, task="charging", charging=True)
    if robot.task == "to_pick":
        return evolve(robot, task="dwell", loaded=True, wait_s=c.dwell_s)
    if robot.task == "to_drop":
        return evolve(robot, task="dwell", loaded=False, wait_s=c.dwell_s)
    if robot.task == "leave_zone":  # out of a new keep-out zone: choose the next job now
        return evolve(robot, task="idle", wait_s=0.0)
    return robot


def _robot_step(state: SimState, robot: Robot, make_rng: Callable[[], random.Random]) -> Robot:
    """One tick of one robot. `make_rng` gives the robot's generator for this tick, made
    only when it picks a new task (seeding one per robot per tick was a tenth of the CPU)."""
    c = state.config
    if robot.task == "charging":
        battery = min(100.0, robot.battery + c.charge_per_s * c.dt_s)
        if battery >= c.full_battery:
            rng = make_rng()
            charged = evolve(
                robot,
                battery=battery,
                charging=False,
                task="idle",
                charge_below=next_charge_level(c, rng),
            )
            robot = _next_task(state, charged, rng)
            # It leaves at once: a robot reporting its new route where it stood charging
            # for longer than the stuck window would look stuck.
            return _drive(state, robot) if robot.waypoints else robot
        return evolve(robot, battery=battery)
    if robot.task in ("dwell", "idle"):
        robot = evolve(
            robot,
            battery=max(0.0, robot.battery - c.idle_drain_per_s * c.dt_s),
            wait_s=robot.wait_s - c.dt_s,
        )
        if robot.wait_s > 0:
            return robot
        waited = robot.task == "idle"  # for a charger, maybe: it may have stood a while
        robot = _next_task(state, robot, make_rng())
        return _drive(state, robot) if waited and robot.waypoints else robot
    if not robot.waypoints:
        return _arrive(state, robot)
    standing = stalled(c, robot, state.t_ms, state.seed, state.tick)
    return standing if standing is not None else _drive(state, robot)


def _drive(state: SimState, robot: Robot) -> Robot:
    """A tick of driving along the waypoints, arriving if they end."""
    c = state.config
    speed_px = speed_at(state, robot.pos) * c.dt_s / state.ros_map.resolution
    # The battery management keeps a reserve for the way to a charger: never drained below.
    reserve = min(robot.battery, RESERVE_BATTERY)
    robot = _advance(robot, speed_px, max(reserve, robot.battery - c.drain_per_s * c.dt_s))
    if not robot.waypoints:
        robot = _arrive(state, robot)
    return robot


def _path_metres(
    state: SimState, robot: Robot, here: tuple[float, float]
) -> tuple[tuple[float, float], ...]:
    """The robot's path in metres: `here` (its position, converted already), then its
    waypoints."""
    if not robot.waypoints:
        return ()
    wps = robot.waypoints[: state.config.max_path_points - 1]
    key = (state.meta, wps)
    tail = _WAYPOINTS_METRES.get(key)
    if tail is None:
        if len(_WAYPOINTS_METRES) > 4096:
            _WAYPOINTS_METRES.clear()
        tail = _WAYPOINTS_METRES[key] = tuple(to_metres(state, p) for p in wps)
    return (here, *tail)


# Waypoints (image points) -> metres: a robot reports the same remaining route for many
# seconds, and converting it point by point at every pose was a sixth of a step's CPU.
# Keyed by the map's geometry too (several maps may be simulated in one process).
_WAYPOINTS_METRES: dict[tuple, tuple] = {}


# --- the step ----------------------------------------------------------------------------


def step(state: SimState) -> tuple[SimState, StepOut]:
    """One tick: maybe change the map, move every robot, report every robot's pose."""
    c = state.config
    out = StepOut()
    t_ms = state.t_ms + int(c.dt_s * 1000)
    state = evolve(state, t_ms=t_ms, tick=state.tick + 1)
    if c.change_every_s > 0 and t_ms >= state.next_change_ms:
        rng = _rng(state.seed, state.tick, "map")
        old_grid = state.grid
        state, chunks, notes = change_map(state, rng)
        out.chunks.extend(chunks)
        out.notes.extend(notes)
        nxt = t_ms + int(rng.expovariate(1.0 / c.change_every_s) * 1000) + 1000
        state = replace(state, next_change_ms=nxt)
        if state.grid is not old_grid:
            state = replace(
                state,
                robots=tuple(replan_blocked(state, r) if r.waypoints else r for r in state.robots),
            )
    robots = []
    traffic = Traffic(state)
    for before in state.robots:
        robot = _robot_step(state, before, partial(_rng, state.seed, state.tick, before.robot_id))
        robot = traffic.move(before, robot)
        robot = network(c, robot, t_ms, state.seed, state.tick)
        robots.append(robot)
        if robot.silent_s > 0:
            continue  # off the network: it reports nothing
        here = to_metres(state, robot.pos)
        x, y = here
        out.poses.append(
            PoseOut(
                robot.robot_id,
                t_ms,
                x,
                y,
                round(robot.yaw, 4),
                round(robot.battery, 1),
                robot.charging,
                robot.loaded,
                _path_metres(state, robot, here),
            )
        )
    return evolve(state, robots=tuple(robots)), out
