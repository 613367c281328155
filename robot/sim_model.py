"""The simulator's state and what a step puts out, and the route planning every part of
it shares (with its cache): plain values, no behaviour. `robot/sim.py` steps the state,
`robot/floor_changes.py` changes the floor, `robot/sim_zones.py` applies operators' zones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

import numpy as np

from mapservice.adapters.ros_map import RosMap
from mapservice.core.events import MapMetaSet

from .chunks import metres_geometry
from .planning import Cell, PlanGrid, plan, route_clear, simplify
from .zones import NO_ZONES, FloorZones

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
    # Incidents as a real floor has them (robot/sim_incidents.py sets them from the incident
    # rules' thresholds; 0: never). Each robot now and then stands still on its route for a
    # while (an obstacle, a person in the way), drops off the network, or drives on below
    # its charge level before it goes to a charger.
    stall_every_s: float = 0.0  # mean time between one robot's stalls
    stall_s: tuple[float, float] = (40.0, 120.0)
    dropout_every_s: float = 0.0  # mean time between one robot's silences
    dropout_s: tuple[float, float] = (15.0, 60.0)
    late_charge_share: float = 0.0  # of the charges, those started late
    late_charge_battery: tuple[float, float] = (8.0, 12.0)  # the level a late one starts at
    # Robots give way (robot/sim_traffic.py): none within this of another, standing for this
    # long at most (0: they drive through each other)
    give_way_m: float = 0.0
    give_way_s: float = 18.0
    station_spacing_m: float = 0.0  # between any two stations or chargers, where there is room


@dataclass(frozen=True)
class Robot:
    robot_id: str
    pos: Point
    yaw: float
    battery: float
    waypoints: tuple[Point, ...] = ()  # still ahead, in order
    task: str = "idle"  # to_pick, to_drop, to_charger, charging, dwell, idle, leave_zone
    target: int = -1  # station (or charger) index the robot drives to
    loaded: bool = False
    wait_s: float = 0.0
    charging: bool = False
    stall_s: float = 0.0  # still standing on its route this long
    silent_s: float = 0.0  # still off the network this long: it reports nothing
    next_stall_ms: int = 0
    next_dropout_ms: int = 0
    charge_below: float = -1.0  # goes to a charger below this level (negative: the config's)
    still_s: float = 0.0  # has stood where it is this long (kept while robots give way)


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
    # Operators' zones. With keep-out zones, `grid` has them blocked (what robots plan on)
    # and `floor_grid` is the floor's own (the way out of a zone, the map changes' checks).
    zones: FloorZones = NO_ZONES
    floor_grid: PlanGrid | None = None

    @property
    def floor(self) -> PlanGrid:
        """The planning grid of the floor alone, keep-out zones not blocked."""
        return self.floor_grid if self.floor_grid is not None else self.grid


@dataclass
class RouteEntry:
    """A planned route in the cache: its cells, their simplified waypoints, and the grid
    it was last found clear on. The grid is replaced whenever the floor changes, so an
    entry checked against the current grid object needs no check again until then."""

    cells: list[Cell]
    waypoints: tuple[Point, ...]
    checked_on: PlanGrid
    # The cells as an (n, 2) array, as `route_clear` checks them: made once per route, not
    # at every check after a floor change.
    cell_array: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.cell_array = np.asarray(self.cells)


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


MAX_CACHED_ROUTES = 4096

_Frozen = TypeVar("_Frozen", Robot, SimState)
_FIELDS: dict[type, frozenset[str]] = {}


def evolve(value: _Frozen, **changes: Any) -> _Frozen:
    """`dataclasses.replace` for the simulator's frozen records, without re-running their
    `__init__`: a copy of the instance's fields with `changes` over them. A simulated week
    replaces robots hundreds of thousands of times, and `replace` was a tenth of its CPU."""
    cls = type(value)
    names = _FIELDS.get(cls)
    if names is None:
        names = _FIELDS[cls] = frozenset(f.name for f in fields(cls))
    if not names.issuperset(changes):
        raise TypeError(f"{cls.__name__} has no field {sorted(set(changes) - names)}")
    new = object.__new__(cls)
    attrs = new.__dict__
    attrs.update(value.__dict__)
    attrs.update(changes)
    return new


# --- geometry and routes -----------------------------------------------------------------


def to_metres(state: SimState, p: Point) -> tuple[float, float]:
    """Continuous image point to world metres (pixel_to_metres is for pixel centres)."""
    meta = state.meta
    known = _GEOMETRY.get(id(meta))
    if known is None or known[0] is not meta:
        if len(_GEOMETRY) > 64:
            _GEOMETRY.clear()
        known = _GEOMETRY[id(meta)] = (meta, *metres_geometry(meta), meta.height)
    _, res, ox, oy, height = known
    # pixel_to_metres' arithmetic step for step (the same floats), on the meta's numbers
    # looked up once: a week of demo history converts millions of points.
    x = ox + (p[0] - 0.5 + 0.5) * res
    y = oy + (height - (p[1] - 0.5) - 0.5) * res
    return round(x, 3), round(y, 3)


# The geometry of each map meta in use (by identity: metas are immutable and long-lived).
_GEOMETRY: dict[int, tuple] = {}


def route_to(state: SimState, robot: Robot, goal: Cell) -> tuple[Point, ...] | None:
    """Waypoints from the robot's next waypoint (or its cell) to the goal cell."""
    start_pt = robot.waypoints[0] if robot.waypoints else robot.pos
    grid = state.grid
    start = grid.cell_at(*start_pt)
    entry = state.routes.get((start, goal))
    if entry is not None and entry.checked_on is not grid:
        # The floor changed since: keep the route only if it is still drivable.
        if route_clear(grid, entry.cell_array):
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
            cells, tuple(grid.centre_px(c) for c in simplify(cells)), grid
        )
    if robot.waypoints:
        return (robot.waypoints[0],) + entry.waypoints[1:]
    return entry.waypoints


def advance_along(
    pos: Point, yaw: float, waypoints: tuple[Point, ...], distance_px: float
) -> tuple[Point, float, int]:
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
