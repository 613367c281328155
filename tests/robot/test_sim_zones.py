"""Operators' zones in the simulator: keep-out zones rasterised into the planning grid with
the robot's radius, the planner around them, robots leaving a zone made around them, and
speed zones lowering the speed (no broker: the pure step function)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mapservice.adapters.costmap_filters import grid_of
from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.annotations import Zone
from mapservice.core.zone_masks import Grid, keep_out_labels, pixel_of, zone_pixels
from mapservice.robot import sim
from mapservice.robot.planning import plan
from mapservice.robot.sim import SimConfig, new_state, step, with_zones
from mapservice.robot.sim_zones import route_cells, speed_at, way_out
from mapservice.robot.zones import blocked_grid, floor_zones, zones_from_listing
from tests.fixtures.paths import MAPS

T0 = 1_795_255_200_000
FREE = Grid(width=200, height=100, resolution=0.05, origin_x=-2.0, origin_y=1.0)


def box(x0: float, y0: float, x1: float, y1: float, kind: str = "keep_out", **kw) -> Zone:
    return Zone(name="z", kind=kind, polygon=((x0, y0), (x1, y0), (x1, y1), (x0, y1)), **kw)


def test_keep_out_pixels_are_the_masks_and_blocked_cells_keep_the_robot_radius_away() -> None:
    zone = box(1.0, 2.0, 2.2, 3.1)
    fz = floor_zones([("k", zone)], FREE, 1.0)
    assert fz.keep_out is not None and fz.speed_m_s is None
    assert np.array_equal(fz.keep_out, zone_pixels(FREE, zone))  # the keep-out mask's pixels
    free = np.ones((FREE.height, FREE.width), dtype=bool)
    radius_m = 0.3
    grid = blocked_grid(free, fz.keep_out, FREE.resolution, 0.25, radius_m)
    inside = np.argwhere(fz.keep_out)  # (row, col) pixels
    for row, col in np.argwhere(np.ones(grid.shape, dtype=bool)):
        u, v = grid.centre_px((int(row), int(col)))
        nearest_m = np.hypot(inside[:, 1] + 0.5 - u, inside[:, 0] + 0.5 - v).min() * FREE.resolution
        if grid.ok[row, col]:
            assert nearest_m >= radius_m, f"ok cell {row, col} is {nearest_m:.2f} m from the zone"
        if nearest_m < 0.01:  # a cell holding zone pixels
            assert not grid.ok[row, col]
    assert grid.ok.sum() > 0.8 * grid.ok.size  # the rest of the floor stays open


def test_the_planner_goes_around_blocked_cells_and_finds_nothing_across_a_closed_aisle() -> None:
    free = np.ones((FREE.height, FREE.width), dtype=bool)
    # A wall of keep-out across the floor's whole height but for a gap at the top.
    wall = floor_zones([("w", box(2.0, 1.0, 2.5, 4.5))], FREE, 1.0).keep_out
    assert wall is not None
    grid = blocked_grid(free, wall, FREE.resolution, 0.25, 0.3)
    start, goal = (grid.shape[0] - 2, 2), (grid.shape[0] - 2, grid.shape[1] - 3)
    path = plan(grid, start, goal)
    assert path is not None and all(grid.ok[c] for c in path)
    assert min(r for r, _ in path) < 10  # up through the gap, not across the wall
    closed = floor_zones([("w", box(2.0, 0.0, 2.5, 7.0))], FREE, 1.0).keep_out
    assert closed is not None
    assert plan(blocked_grid(free, closed, FREE.resolution, 0.25, 0.3), start, goal) is None
    assert plan(blocked_grid(free, np.zeros_like(free), FREE.resolution, 0.25, 0.3), start, goal)


def test_speed_limits_per_pixel_percent_of_top_speed_or_m_s_lowest_wins() -> None:
    half = box(-2.0, 1.0, 3.0, 6.0, "speed_limit", speed_limit=50, speed_unit="percent")
    slow = box(-1.0, 2.0, 0.0, 3.0, "speed_limit", speed_limit=0.2, speed_unit="m/s")
    note = box(-2.0, 1.0, 8.0, 6.0, "note")
    fz = floor_zones([("a", half), ("b", slow), ("n", note)], FREE, 1.5)
    assert fz.keep_out is None and fz.speed_m_s is not None
    at = lambda x, y: float(fz.speed_m_s[pixel_of(FREE, x, y)])  # noqa: E731
    assert at(2.0, 4.0) == pytest.approx(0.75)
    assert at(-0.5, 2.5) == pytest.approx(0.2)
    assert at(5.0, 4.0) == math.inf


def test_zones_from_the_api_listing() -> None:
    listing = {
        "at_ms": 1,
        "annotations": [
            {
                "id": "p",
                "annotation": {"shape": "poi", "name": "s", "kind": "station", "x": 1, "y": 2},
            },
            {
                "id": "z",
                "annotation": {
                    "shape": "zone",
                    "name": "k",
                    "kind": "keep_out",
                    "polygon": [[0, 0], [1, 0], [1, 1]],
                    "holes": [],
                },
            },
        ],
    }
    [(zone_id, zone)] = zones_from_listing(listing)
    assert zone_id == "z" and zone.kind == "keep_out" and zone.polygon[1] == (1.0, 0.0)
    with pytest.raises(ValueError, match="annotations"):
        zones_from_listing({"detail": "Not Found"})


# --- the simulation -------------------------------------------------------------------------


def depot(robots: int = 6, change_every_s: float = 8):
    return new_state(
        load_ros_map(MAPS / "depot.yaml"),
        robots,
        seed=3,
        t_ms=T0,
        config=SimConfig(change_every_s=change_every_s),
    )


def metres(state, p):
    return sim.to_metres(state, p)


def poses_inside(state, out, zones) -> list:
    """The poses the processors' zone watch would call violations (the masks' pixel rule)."""
    grid = grid_of(state.meta)
    labels, _ids = keep_out_labels(grid, zones)
    return [p for p in out.poses if (px := pixel_of(grid, p.x, p.y)) and labels[px]]


def zone_on_a_route(state, half_m: float = 0.8) -> tuple[Zone, str]:
    """A keep-out square on a stretch some robot is about to drive, with no robot in or near
    it: (the zone, the robot whose route crossed it)."""
    for robot in state.robots:
        for a in robot.waypoints[1:]:
            x, y = metres(state, a)
            if all(math.dist((x, y), metres(state, r.pos)) > half_m + 1.0 for r in state.robots):
                return box(x - half_m, y - half_m, x + half_m, y + half_m), robot.robot_id
    raise AssertionError("no robot drives anywhere")


def test_robots_plan_around_a_new_keep_out_zone_and_never_stand_in_it() -> None:
    state = depot()
    for _ in range(30):
        state, _out = step(state)
    zone, crossing = zone_on_a_route(state)
    before = next(r for r in state.robots if r.robot_id == crossing)
    grid_before = state.grid
    zones = [("k1", zone)]
    state, notes = with_zones(state, zones)
    assert notes == []  # nobody stood in it
    assert state.grid is not grid_before and state.routes == {}
    after = next(r for r in state.robots if r.robot_id == crossing)
    assert after.waypoints != before.waypoints  # replanned around it
    assert all(state.grid.ok[c] for c in route_cells(state.grid, (after.pos, *after.waypoints)))
    moved = 0
    for _ in range(400):  # with map changes: they re-plan on the zoned grid too
        state, out = step(state)
        assert poses_inside(state, out, zones) == []
        for pose in out.poses:
            for x, y in pose.path:  # nor do they publish a path through it
                px = pixel_of(grid_of(state.meta), x, y)
                assert px is None or not state.zones.keep_out[px]
        moved += sum(1 for r in state.robots if r.task.startswith("to_"))
    assert moved > 400  # the robots kept working


def test_a_robot_inside_a_new_zone_leaves_it_by_the_shortest_way_and_stays_out() -> None:
    state = depot(change_every_s=0)
    for _ in range(20):
        state, _out = step(state)
    robot = next(r for r in state.robots if r.task.startswith("to_"))
    x, y = metres(state, robot.pos)
    zones = [("around", box(x - 0.6, y - 0.6, x + 0.6, y + 0.6))]
    state, notes = with_zones(state, zones)
    assert any(n.startswith(f"{robot.robot_id} leaves a keep-out zone") for n in notes)
    leaving = next(r for r in state.robots if r.robot_id == robot.robot_id)
    assert leaving.task == "leave_zone"
    out_in = None
    for i in range(60):
        state, out = step(state)
        inside = {p.robot_id for p in poses_inside(state, out, zones)}
        if robot.robot_id not in inside and out_in is None:
            out_in = i + 1
        if out_in is not None:
            assert robot.robot_id not in inside, "it came back into the zone"
    assert out_in is not None and out_in <= 2  # 0.6 m and the radius at 1 m/s
    assert next(r for r in state.robots if r.robot_id == robot.robot_id).task != "leave_zone"


def test_a_robot_walled_in_by_a_zone_stops_and_says_so() -> None:
    state = depot(robots=2, change_every_s=0)
    w, h = state.meta.width * state.meta.resolution, state.meta.height * state.meta.resolution
    state, notes = with_zones(state, [("all", box(-1, -1, w + 1, h + 1))])
    assert len(notes) == 2 and all("no way out" in n for n in notes)
    assert way_out(state.floor, state.grid, state.grid.cell_at(*state.robots[0].pos)) is None
    before = [r.pos for r in state.robots]
    for _ in range(20):
        state, _out = step(state)
    assert [r.pos for r in state.robots] == before


def test_a_speed_zone_lowers_the_speed_inside_it_and_only_there() -> None:
    state = depot(change_every_s=0)
    w, h = state.meta.width * state.meta.resolution, state.meta.height * state.meta.resolution
    slow = box(-1, -1, w / 2, h + 1, "speed_limit", speed_limit=25, speed_unit="percent")
    state, notes = with_zones(state, [("slow", slow)])
    assert notes == []
    grid = grid_of(state.meta)
    inside = zone_pixels(grid, slow)
    last: dict[str, tuple[float, float]] = {}
    fast_outside = slow_inside = 0
    for _ in range(300):
        started = {r.robot_id: r.pos for r in state.robots}
        state, out = step(state)
        for pose in out.poses:
            u, v = started[pose.robot_id]
            was_inside = bool(inside[int(v), int(u)])
            if pose.robot_id in last:
                d = math.dist(last[pose.robot_id], (pose.x, pose.y))
                if was_inside:
                    assert d <= 0.25 + 0.01
                    slow_inside += d > 0.2
                elif d > 0.9:
                    fast_outside += 1
            last[pose.robot_id] = (pose.x, pose.y)
    assert slow_inside > 10 and fast_outside > 10
    # Taking the zone away gives the robots their speed back everywhere.
    state, _ = with_zones(state, [])
    assert state.zones.speed_m_s is None and speed_at(state, state.robots[0].pos) == 1.0


def test_a_cached_route_through_a_new_zone_is_not_reused() -> None:
    state = depot(robots=1, change_every_s=0)
    robot = replace(state.robots[0], waypoints=())
    goal = max(state.stations, key=lambda c: math.dist(c, state.grid.cell_at(*robot.pos)))
    first = sim._route(state, robot, goal)
    assert first is not None
    mid = metres(state, first[len(first) // 2])
    zones = [("k", box(mid[0] - 0.5, mid[1] - 0.5, mid[0] + 0.5, mid[1] + 0.5))]
    state, _ = with_zones(state, zones)
    again = sim._route(state, robot, goal)
    assert again is not None and again != first
    assert all(state.grid.ok[c] for c in route_cells(state.grid, (robot.pos, *again)))
