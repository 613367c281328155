"""The floor changing under the simulated robots: a pallet appears or is taken away, a door
closes or opens. A change is published as the chunks it touched, by the robot nearest to
it, and robots whose route it blocks plan again.
"""

from __future__ import annotations

import math
import random
from dataclasses import replace

import numpy as np

from mapservice.adapters.ros_map import RosMap, drivable

from .chunks import chunk_pixels
from .planning import dilate, largest_component, segment_pixels
from .sim_model import ChunkOut, MapChange, Robot, SimState, route_to, to_metres
from .sim_zones import plan_grids


def _protected(state: SimState) -> np.ndarray:
    """Coarse cells a new obstacle must stay clear of: where robots are and the stretch
    they drive next (a replan keeps its first waypoint, so that stretch must stay open)."""
    g = state.grid
    mask = np.zeros(g.shape, dtype=bool)
    for r in state.robots:
        ahead = segment_pixels(r.pos, r.waypoints[0], step=g.cell_px / 2) if r.waypoints else ()
        for p in (r.pos, *ahead):
            row, col = g.cell_at(*p)
            mask[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2] = True
    for cell in (*state.stations, *state.chargers):
        mask[cell] = True
    inflate = max(
        1, math.ceil(state.config.robot_radius_m / (g.cell_px * state.ros_map.resolution))
    )
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
        if (
            row0 >= 0
            and col0 >= 0
            and box[2] <= m.height
            and box[3] <= m.width
            and state.drivable[row0 : box[2], col0 : box[3]].all()
        ):
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


def _with_pixels(
    state: SimState, pixels: np.ndarray, box: tuple[int, int, int, int] | None = None
) -> SimState:
    """The state on the map `pixels`. With `box` (row0, col0, row1, col1, exclusive), the
    only pixels that differ from the state's map: only they are classified again (a pixel
    is drivable or not by its own value), not the whole image at every floor change."""
    m = state.ros_map.with_pixels(pixels)
    if box is None:
        free = drivable(m)
    else:
        r0, c0, r1, c1 = box
        free = state.drivable.copy()
        free[r0:r1, c0:c1] = drivable(m.with_pixels(pixels[r0:r1, c0:c1]))
    grid, floor_grid = plan_grids(free, state.zones, m.resolution, state.config)
    return replace(state, ros_map=m, drivable=free, grid=grid, floor_grid=floor_grid)


def _touched_chunks(
    state: SimState, box: tuple[int, int, int, int], robot_id: str
) -> list[ChunkOut]:
    meta = state.meta
    r0, c0, r1, c1 = box
    fill = state.ros_map.unknown_value
    out = []
    for row in range(r0 // meta.chunk_height, (r1 - 1) // meta.chunk_height + 1):
        for col in range(c0 // meta.chunk_width, (c1 - 1) // meta.chunk_width + 1):
            out.append(
                ChunkOut(
                    robot_id,
                    state.t_ms,
                    row,
                    col,
                    chunk_pixels(state.ros_map.pixels, meta, row, col, fill),
                )
            )
    return out


def _nearest_robot(state: SimState, box: tuple[int, int, int, int]) -> str:
    centre = ((box[1] + box[3]) / 2, (box[0] + box[2]) / 2)
    if not state.robots:
        return "sim-floor"
    return min(state.robots, key=lambda r: math.dist(r.pos, centre)).robot_id


def change_map(state: SimState, rng: random.Random) -> tuple[SimState, list[ChunkOut], list[str]]:
    c = state.config
    due = [ch for ch in state.changes if ch.until_ms <= state.t_ms]
    if due:  # take the oldest change back first: the pallet is moved off, the door opens
        change = due[0]
        r0, c0, r1, c1 = change.pixels
        pixels = state.ros_map.pixels.copy()
        pixels[r0:r1, c0:c1] = np.frombuffer(change.before, np.uint8).reshape(r1 - r0, c1 - c0)
        state = _with_pixels(
            replace(state, changes=tuple(x for x in state.changes if x is not change)),
            pixels,
            change.pixels,
        )
        what = "pallet taken away" if change.kind == "pallet" else "door opened"
        return (
            state,
            _touched_chunks(state, change.pixels, _nearest_robot(state, change.pixels)),
            [what],
        )
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
    new = _with_pixels(replace(state, changes=state.changes + (change,)), pixels, box)
    # On the floor alone: a station inside a keep-out zone is unreachable while the zone
    # stands, and no map change could ever pass this check.
    reachable = largest_component(new.floor.ok)
    if not all(reachable[cell] for cell in (*state.stations, *state.chargers)):
        return state, [], []  # it would cut a station off from the others: not there
    x, y = to_metres(state, ((c0 + c1) / 2, (r0 + r1) / 2))
    what = "pallet appeared" if kind == "pallet" else "door closed"
    return (
        new,
        _touched_chunks(new, box, _nearest_robot(new, box)),
        [f"{what} at ({x:.1f}, {y:.1f}) m"],
    )


def replan_blocked(state: SimState, robot: Robot) -> Robot:
    """A robot whose route crosses a cell that is no longer ok plans again (one leaving a
    keep-out zone drives on: its way out crosses blocked cells on purpose)."""
    if robot.task == "leave_zone":
        return robot
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
    route = route_to(state, robot, goal)
    if route is not None:
        return replace(robot, waypoints=route)
    # The goal is walled off: stop at the next waypoint and choose again from there.
    return replace(
        robot, waypoints=robot.waypoints[:1], task="idle" if not robot.loaded else robot.task
    )
