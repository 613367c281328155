"""A simulated shift on a real map, as a pure step function over a state.

`new_state(map, robots, seed)` places stations and robots; `step(state)` advances one tick
and returns the next state and what the robots would publish during it (poses with their
planned path, chunks of map changes). Nothing here touches a clock, a socket or a global
random generator: tests drive it for thousands of steps without a broker, and the runner
(`robot/simrun.py`) only encodes and publishes the outputs.

Robots cycle pick station -> drop station (loaded) -> next job, go to a charger below
`low_battery`, and never leave the inflated free space of the planning grid. Now and
then the floor changes (a pallet appears or is taken away, a door closes or opens); the
change is published as the chunks it touched, by the robot nearest to it.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from mapservice.core.events import MapMetaSet
from mapservice.adapters.ros_map import RosMap, drivable, meta_for

from .chunks import chunk_pixels, pixel_to_metres
from .planning import (Cell, PlanGrid, dilate, grid_for, largest_component, plan, plan_cell_sizes,
                       route_clear, segment_pixels, simplify)

Point = tuple[float, float]  # continuous image coordinates (u = column, v = row)


def sim_robot_id(prefix: str, i: int) -> str:
    """The id of the shift simulator's robot number `i` (`up --auth` gives each its credential)."""
    return f"{prefix}-{i:03d}"


@dataclass(frozen=True)
class SimConfig:
    dt_s: float = 1.0
    speed_m_s: float = 1.0
    cell_m: float = 0.25
    robot_radius_m: float = 0.3
    stations: int = 8
    chargers: int = 2
    dwell_s: float = 5.0
    drain_per_s: float = 0.12  # % while driving
    idle_drain_per_s: float = 0.02
    charge_per_s: float = 1.5
    low_battery: float = 25.0
    full_battery: float = 95.0
    change_every_s: float = 20.0  # mean time between map changes (0: never)
    max_changes: int = 6  # open changes (pallets standing, doors closed) at once
    pallet_m: tuple[float, float] = (1.0, 1.2)
    door_max_m: float = 3.0
    max_path_points: int = 1000


@dataclass(frozen=True)
class Robot:
    robot_id: str
    pos: Point
    yaw: float
    battery: float
    waypoints: tuple[Point, ...] = ()  # still ahead, in order
    task: str = "idle"  # to_pick, to_drop, to_charger, charging, dwell, idle
    target: int = -1  # station (or charger) index the robot drives to
    loaded: bool = False
    wait_s: float = 0.0
    charging: bool = False


@dataclass(frozen=True)
class MapChange:
    kind: str  # pallet or door
    pixels: tuple[int, int, int, int]  # row0, col0, row1, col1 (exclusive) of the patch
    before: bytes  # what the patch held, to take the change back
    until_ms: int


@dataclass(frozen=True)
class SimState:
    ros_map: RosMap  # the current map (pixels change with the floor)
    meta: MapMetaSet
    config: SimConfig
    grid: PlanGrid
    drivable: np.ndarray
    stations: tuple[Cell, ...]
    chargers: tuple[Cell, ...]
    robots: tuple[Robot, ...]
    t_ms: int
    seed: int
    tick: int = 0
    changes: tuple[MapChange, ...] = ()
    next_change_ms: int = 0
    # (start cell, goal cell) -> RouteEntry, shared by every later state. Robots start
    # most routes at a station, so a handful of routes recur all shift; A* is most of the
    # simulator's CPU, and a route still clear on today's grid is reused.
    routes: dict = field(default_factory=dict, compare=False, repr=False)


@dataclass
class RouteEntry:
    """A planned route in the cache: its cells, their simplified waypoints, and the grid
    it was last found clear on. The grid is replaced whenever the floor changes, so an
    entry checked against the current grid object needs no check again until then."""
    cells: list[Cell]
    waypoints: tuple[Point, ...]
    checked_on: PlanGrid


@dataclass(frozen=True)
class PoseOut:
    robot_id: str
    t_ms: int
    x: float
    y: float
    yaw: float
    battery: float
    charging: bool
    loaded: bool
    path: tuple[tuple[float, float], ...]  # metres, from the robot's position to its goal


@dataclass(frozen=True)
class ChunkOut:
    robot_id: str
    t_ms: int
    row: int
    column: int
    pixels: bytes


@dataclass(frozen=True)
class StepOut:
    poses: list[PoseOut] = field(default_factory=list)
    chunks: list[ChunkOut] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # human-readable: "pallet appeared ..."


# --- set-up ------------------------------------------------------------------------------


def _rng(seed: int, tick: int, salt: str = "") -> random.Random:
    return random.Random(f"{seed}:{tick}:{salt}")


def new_state(ros_map: RosMap, robots: int, *, seed: int = 7, t_ms: int = 0,
              config: SimConfig = SimConfig(), prefix: str = "sim", chunk_width: int = 100,
              chunk_height: int = 100) -> SimState:
    free = drivable(ros_map)
    config, grid, cells = _plan_grid(free, ros_map.resolution, config, robots)
    rng = _rng(seed, -1, "setup")
    picked = rng.sample(cells, config.stations + config.chargers)
    stations, chargers = tuple(picked[: config.stations]), tuple(picked[config.stations:])
    fleet = []
    for i, cell in enumerate(rng.sample(cells, min(robots, capacity(len(cells))))):
        fleet.append(Robot(sim_robot_id(prefix, i), grid.centre_px(cell), rng.uniform(-math.pi, math.pi),
                           battery=round(rng.uniform(40, 100), 1)))
    return SimState(ros_map, meta_for(ros_map, chunk_width, chunk_height), config, grid, free,
                    stations, chargers, tuple(fleet), t_ms, seed,
                    next_change_ms=t_ms + int(config.change_every_s * 1000))


MAX_CACHED_ROUTES = 4096


def capacity(reachable_cells: int) -> int:
    """How many robots a connected free area of that many planning cells hosts: each
    starts on a cell of its own and keeps room to move (a quarter of the cells)."""
    return max(1, reachable_cells // 4)


def _plan_grid(free: np.ndarray, resolution: float, config: SimConfig,
               robots: int) -> tuple[SimConfig, PlanGrid, list[Cell]]:
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
            "robot); use a map with more free space")
    return best


# --- geometry ----------------------------------------------------------------------------


def to_metres(state: SimState, p: Point) -> tuple[float, float]:
    """Continuous image point to world metres (pixel_to_metres is for pixel centres)."""
    x, y = pixel_to_metres(p[0] - 0.5, p[1] - 0.5, state.meta)
    return round(x, 3), round(y, 3)


def _route(state: SimState, robot: Robot, goal: Cell) -> tuple[Point, ...] | None:
    """Waypoints from the robot's next waypoint (or its cell) to the goal cell."""
    start_pt = robot.waypoints[0] if robot.waypoints else robot.pos
    grid = state.grid
    start = grid.cell_at(*start_pt)
    entry = state.routes.get((start, goal))
    if entry is not None and entry.checked_on is not grid:
        # The floor changed since: keep the route only if it is still drivable.
        if route_clear(grid, entry.cells):
            entry.checked_on = grid
        else:
            entry = None
    if entry is None:
        cells = plan(grid, start, goal)
        if cells is None:
            return None
        if len(state.routes) > MAX_CACHED_ROUTES:
            state.routes.clear()
        entry = state.routes[(start, goal)] = RouteEntry(
            cells, tuple(grid.centre_px(c) for c in simplify(cells)), grid)
    if robot.waypoints:
        return (robot.waypoints[0],) + entry.waypoints[1:]
    return entry.waypoints


def advance_along(pos: Point, yaw: float, waypoints: tuple[Point, ...],
                  distance_px: float) -> tuple[Point, float, int]:
    """Where driving `distance_px` along the waypoints from `pos` ends: the position, the
    heading, and how many waypoints it reached. Plain values, no Robot: the demo history
    interpolates poses between steps with it millions of times."""
    passed, n = 0, len(waypoints)
    while passed < n and distance_px > 1e-9:
        tx, ty = waypoints[passed]
        d = math.hypot(tx - pos[0], ty - pos[1])
        if d > 1e-9:
            yaw = math.atan2(-(ty - pos[1]), tx - pos[0])  # image rows grow downwards
        if d <= distance_px:
            pos, distance_px = (tx, ty), distance_px - d
            passed += 1
        else:
            f = distance_px / d
            pos, distance_px = (pos[0] + (tx - pos[0]) * f, pos[1] + (ty - pos[1]) * f), 0.0
    return pos, yaw, passed


def _advance(robot: Robot, distance_px: float) -> Robot:
    pos, yaw, passed = advance_along(robot.pos, robot.yaw, robot.waypoints, distance_px)
    return replace(robot, pos=pos, waypoints=robot.waypoints[passed:], yaw=yaw)


# --- behaviour ---------------------------------------------------------------------------


def _next_task(state: SimState, robot: Robot, rng: random.Random) -> Robot:
    """Picks what to do next and plans the route; stays put if nothing is reachable."""
    if robot.battery < state.config.low_battery and robot.task != "to_charger":
        options = [("to_charger", i, c) for i, c in enumerate(state.chargers)]
    elif robot.loaded:
        options = [("to_drop", i, c) for i, c in enumerate(state.stations) if i != robot.target]
    else:
        options = [("to_pick", i, c) for i, c in enumerate(state.stations) if i != robot.target]
    rng.shuffle(options)
    if robot.task == "to_charger" or (options and options[0][0] == "to_charger"):
        here = robot.pos
        options.sort(key=lambda o: math.dist(here, state.grid.centre_px(o[2])))
    for task, index, cell in options[:3]:
        route = _route(state, robot, cell)
        if route is not None:
            return replace(robot, task=task, target=index, waypoints=route)
    return replace(robot, task="idle", wait_s=state.config.dwell_s)


def _arrive(state: SimState, robot: Robot) -> Robot:
    c = state.config
    if robot.task == "to_charger":
        return replace(robot, task="charging", charging=True)
    if robot.task == "to_pick":
        return replace(robot, task="dwell", loaded=True, wait_s=c.dwell_s)
    if robot.task == "to_drop":
        return replace(robot, task="dwell", loaded=False, wait_s=c.dwell_s)
    return robot


def _robot_step(state: SimState, robot: Robot, make_rng: Callable[[], random.Random]) -> Robot:
    """One tick of one robot. `make_rng` gives the robot's generator for this tick, made
    only when it picks a new task (seeding one per robot per tick was a tenth of the CPU)."""
    c = state.config
    if robot.task == "charging":
        battery = min(100.0, robot.battery + c.charge_per_s * c.dt_s)
        if battery >= c.full_battery:
            return _next_task(state, replace(robot, battery=battery, charging=False, task="idle"), make_rng())
        return replace(robot, battery=battery)
    if robot.task in ("dwell", "idle"):
        robot = replace(robot, battery=max(0.0, robot.battery - c.idle_drain_per_s * c.dt_s),
                        wait_s=robot.wait_s - c.dt_s)
        return _next_task(state, robot, make_rng()) if robot.wait_s <= 0 else robot
    if not robot.waypoints:
        return _arrive(state, robot)
    speed_px = c.speed_m_s * c.dt_s / state.ros_map.resolution
    robot = _advance(robot, speed_px)
    robot = replace(robot, battery=max(0.0, robot.battery - c.drain_per_s * c.dt_s))
    if not robot.waypoints:
        robot = _arrive(state, robot)
    return robot


def _path_metres(state: SimState, robot: Robot) -> tuple[tuple[float, float], ...]:
    if not robot.waypoints:
        return ()
    wps = robot.waypoints[: state.config.max_path_points - 1]
    key = (state.meta, wps)
    tail = _WAYPOINTS_METRES.get(key)
    if tail is None:
        if len(_WAYPOINTS_METRES) > 4096:
            _WAYPOINTS_METRES.clear()
        tail = _WAYPOINTS_METRES[key] = tuple(to_metres(state, p) for p in wps)
    return (to_metres(state, robot.pos), *tail)


# Waypoints (image points) -> metres: a robot reports the same remaining route for many
# seconds, and converting it point by point at every pose was a sixth of a step's CPU.
# Keyed by the map's geometry too (several maps may be simulated in one process).
_WAYPOINTS_METRES: dict[tuple, tuple] = {}


# --- map changes -------------------------------------------------------------------------


def _protected(state: SimState) -> np.ndarray:
    """Coarse cells a new obstacle must stay clear of: where robots are and the stretch
    they drive next (a replan keeps its first waypoint, so that stretch must stay open)."""
    g = state.grid
    mask = np.zeros(g.shape, dtype=bool)
    for r in state.robots:
        ahead = segment_pixels(r.pos, r.waypoints[0], step=g.cell_px / 2) if r.waypoints else ()
        for p in (r.pos, *ahead):
            row, col = g.cell_at(*p)
            mask[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2] = True
    for cell in (*state.stations, *state.chargers):
        mask[cell] = True
    inflate = max(1, math.ceil(state.config.robot_radius_m / (g.cell_px * state.ros_map.resolution)))
    return dilate(mask, inflate + 1)


def _occupied_value(m: RosMap) -> int:
    return 255 if m.negate else 0


def _pallet(state: SimState, rng: random.Random) -> tuple[int, int, int, int] | None:
    m, g = state.ros_map, state.grid
    h = max(1, round(state.config.pallet_m[0] / m.resolution))
    w = max(1, round(state.config.pallet_m[1] / m.resolution))
    if rng.random() < 0.5:
        h, w = w, h
    ok = np.argwhere(g.ok)
    for _ in range(20):
        r, c = ok[rng.randrange(len(ok))]
        u, v = g.centre_px((int(r), int(c)))
        row0, col0 = int(v) - h // 2, int(u) - w // 2
        box = (row0, col0, row0 + h, col0 + w)
        if row0 >= 0 and col0 >= 0 and box[2] <= m.height and box[3] <= m.width \
                and state.drivable[row0:box[2], col0:box[3]].all():
            return box
    return None


def _door(state: SimState, rng: random.Random) -> tuple[int, int, int, int] | None:
    """A wall across a narrow passage: from a free pixel, walls within door_max_m on both
    sides (left/right or up/down)."""
    m, free = state.ros_map, state.drivable
    max_px = round(state.config.door_max_m / m.resolution)
    thick = max(2, round(0.1 / m.resolution))
    ok = np.argwhere(state.grid.ok)
    for _ in range(40):
        r, c = ok[rng.randrange(len(ok))]
        u, v = (int(x) for x in state.grid.centre_px((int(r), int(c))))
        horizontal = rng.random() < 0.5
        line = free[v, :] if horizontal else free[:, u]
        at = u if horizontal else v
        lo, hi = at, at
        while lo > 0 and line[lo - 1] and at - lo < max_px:
            lo -= 1
        while hi < len(line) - 1 and line[hi + 1] and hi - at < max_px:
            hi += 1
        if lo == 0 or hi == len(line) - 1 or line[lo - 1] or line[hi + 1] or hi - lo >= max_px:
            continue  # not closed off by walls on both sides within reach
        if hi - lo < round(0.6 / m.resolution):
            continue
        if horizontal:
            return (v - thick // 2, lo, v - thick // 2 + thick, hi + 1)
        return (lo, u - thick // 2, hi + 1, u - thick // 2 + thick)
    return None


def _with_pixels(state: SimState, pixels: np.ndarray) -> SimState:
    m = state.ros_map.with_pixels(pixels)
    free = drivable(m)
    grid = grid_for(free, m.resolution, state.config.cell_m, state.config.robot_radius_m)
    return replace(state, ros_map=m, drivable=free, grid=grid)


def _touched_chunks(state: SimState, box: tuple[int, int, int, int], robot_id: str) -> list[ChunkOut]:
    meta = state.meta
    r0, c0, r1, c1 = box
    fill = state.ros_map.unknown_value
    out = []
    for row in range(r0 // meta.chunk_height, (r1 - 1) // meta.chunk_height + 1):
        for col in range(c0 // meta.chunk_width, (c1 - 1) // meta.chunk_width + 1):
            out.append(ChunkOut(robot_id, state.t_ms, row, col,
                                chunk_pixels(state.ros_map.pixels, meta, row, col, fill)))
    return out


def _nearest_robot(state: SimState, box: tuple[int, int, int, int]) -> str:
    centre = ((box[1] + box[3]) / 2, (box[0] + box[2]) / 2)
    if not state.robots:
        return "sim-floor"
    return min(state.robots, key=lambda r: math.dist(r.pos, centre)).robot_id


def _change_map(state: SimState, rng: random.Random) -> tuple[SimState, list[ChunkOut], list[str]]:
    c = state.config
    due = [ch for ch in state.changes if ch.until_ms <= state.t_ms]
    if due:  # take the oldest change back first: the pallet is moved off, the door opens
        change = due[0]
        r0, c0, r1, c1 = change.pixels
        pixels = state.ros_map.pixels.copy()
        pixels[r0:r1, c0:c1] = np.frombuffer(change.before, np.uint8).reshape(r1 - r0, c1 - c0)
        state = _with_pixels(replace(state, changes=tuple(x for x in state.changes if x is not change)),
                             pixels)
        what = "pallet taken away" if change.kind == "pallet" else "door opened"
        return state, _touched_chunks(state, change.pixels, _nearest_robot(state, change.pixels)), [what]
    if len(state.changes) >= c.max_changes:
        return state, [], []
    kind = "pallet" if rng.random() < 0.6 else "door"
    box = _pallet(state, rng) if kind == "pallet" else _door(state, rng)
    if box is None:
        return state, [], []
    r0, c0, r1, c1 = box
    protected = _protected(state)
    g = state.grid
    cr0, cc0 = r0 // g.cell_px, c0 // g.cell_px
    cr1, cc1 = (r1 - 1) // g.cell_px + 1, (c1 - 1) // g.cell_px + 1
    if protected[cr0:cr1, cc0:cc1].any():
        return state, [], []  # a robot or a station is too close: not this time
    pixels = state.ros_map.pixels.copy()
    before = pixels[r0:r1, c0:c1].tobytes()
    pixels[r0:r1, c0:c1] = _occupied_value(state.ros_map)
    hold_ms = int(rng.uniform(2, 6) * c.change_every_s * 1000)
    change = MapChange(kind, box, before, state.t_ms + hold_ms)
    new = _with_pixels(replace(state, changes=state.changes + (change,)), pixels)
    reachable = largest_component(new.grid.ok)
    if not all(reachable[cell] for cell in (*state.stations, *state.chargers)):
        return state, [], []  # it would cut a station off from the others: not there
    x, y = to_metres(state, ((c0 + c1) / 2, (r0 + r1) / 2))
    what = "pallet appeared" if kind == "pallet" else "door closed"
    return new, _touched_chunks(new, box, _nearest_robot(new, box)), [f"{what} at ({x:.1f}, {y:.1f}) m"]


def _replan_blocked(state: SimState, robot: Robot) -> Robot:
    """A robot whose route crosses a cell that is no longer ok plans again."""
    g = state.grid
    pts = [robot.pos, *robot.waypoints]
    blocked = False
    for a, b in zip(pts, pts[1:]):
        cells = {g.cell_at(u, v) for u, v in segment_pixels(a, b, step=g.cell_px / 2)}
        if not all(g.is_ok(cell) for cell in cells):
            blocked = True
            break
    if not blocked:
        return robot
    goal = g.cell_at(*robot.waypoints[-1])
    route = _route(state, robot, goal)
    if route is not None:
        return replace(robot, waypoints=route)
    # The goal is walled off: stop at the next waypoint and choose again from there.
    return replace(robot, waypoints=robot.waypoints[:1], task="idle" if not robot.loaded else robot.task)


# --- the step ----------------------------------------------------------------------------


def step(state: SimState) -> tuple[SimState, StepOut]:
    """One tick: maybe change the map, move every robot, report every robot's pose."""
    c = state.config
    out = StepOut()
    t_ms = state.t_ms + int(c.dt_s * 1000)
    state = replace(state, t_ms=t_ms, tick=state.tick + 1)
    if c.change_every_s > 0 and t_ms >= state.next_change_ms:
        rng = _rng(state.seed, state.tick, "map")
        old_grid = state.grid
        state, chunks, notes = _change_map(state, rng)
        out.chunks.extend(chunks)
        out.notes.extend(notes)
        nxt = t_ms + int(rng.expovariate(1.0 / c.change_every_s) * 1000) + 1000
        state = replace(state, next_change_ms=nxt)
        if state.grid is not old_grid:
            state = replace(state, robots=tuple(
                _replan_blocked(state, r)
                if r.waypoints else r for r in state.robots))
    robots = []
    for robot in state.robots:
        robot = _robot_step(state, robot, partial(_rng, state.seed, state.tick, robot.robot_id))
        robots.append(robot)
        x, y = to_metres(state, robot.pos)
        out.poses.append(PoseOut(robot.robot_id, t_ms, x, y, round(robot.yaw, 4),
                                 round(robot.battery, 1), robot.charging, robot.loaded,
                                 _path_metres(state, robot)))
    return replace(state, robots=tuple(robots)), out
