"""Robots keep to the right of their route's centre line where the floor has room: a route
kept to the side never leaves the ok cells of the planning grid (so never touches a blocked
pixel), starts and ends at its cells' centres (stations and chargers), and two robots meeting
head-on in an aisle pass more than a near miss apart, where down its middle they met."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.adapters.ros_map import RosMap, drivable, load_ros_map
from mapservice.robot import DEFAULT_MAP
from mapservice.robot.planning import grid_for, largest_component, path_is_clear, plan
from mapservice.robot.sim_lanes import keep_to_side, segment_cells

NEAR_MISS_M = 1.0


def _ok_cells(grid) -> list[tuple[int, int]]:
    return list(zip(*(a.tolist() for a in np.nonzero(largest_component(grid.ok))), strict=True))


def _assert_on_ok_cells(grid, free, cells, route) -> None:
    """Every point of the route, walked in steps of a tenth of a pixel, lies on an ok cell
    (a check of its own, not `segment_cells`), and no pixel under it is blocked."""
    assert route[0] == grid.centre_px(cells[0]) and route[-1] == grid.centre_px(cells[-1])
    for (u0, v0), (u1, v1) in zip(route, route[1:], strict=False):
        n = max(1, math.ceil(math.hypot(u1 - u0, v1 - v0) * 10))
        for k in range(n + 1):
            u, v = u0 + (u1 - u0) * k / n, v0 + (v1 - v0) * k / n
            assert grid.is_ok(grid.cell_at(u, v)), f"off the ok cells at {u:.1f}, {v:.1f}"
    assert path_is_clear(list(route), free)


@pytest.fixture(scope="module")
def demo_floor():
    ros_map = load_ros_map(DEFAULT_MAP)
    free = drivable(ros_map)
    grid = grid_for(free, ros_map.resolution)
    return ros_map, free, grid, _ok_cells(grid)


@settings(max_examples=60, deadline=None)
@given(st.randoms(use_true_random=False), st.floats(0.0, 2.5))
def test_routes_kept_to_the_side_on_the_demo_floor_stay_on_ok_cells(
    demo_floor, rng, offset_m
) -> None:
    ros_map, free, grid, cells = demo_floor
    start, goal = rng.sample(cells, 2)
    planned = plan(grid, start, goal)
    assert planned is not None
    _assert_on_ok_cells(
        grid, free, planned, keep_to_side(grid, planned, offset_m / ros_map.resolution)
    )


@st.composite
def floors(draw):
    """A walled floor with random racks (occupied rectangles), and two of its free cells."""
    height, width = draw(st.integers(60, 160)), draw(st.integers(60, 160))
    pixels = np.full((height, width), 254, dtype=np.uint8)
    pixels[:3, :] = pixels[-3:, :] = pixels[:, :3] = pixels[:, -3:] = 0
    for _ in range(draw(st.integers(0, 8))):
        r, c = draw(st.integers(0, height - 1)), draw(st.integers(0, width - 1))
        pixels[r : r + draw(st.integers(2, 40)), c : c + draw(st.integers(2, 40))] = 0
    ros_map = RosMap(pixels, 0.05, (0.0, 0.0, 0.0))
    free = drivable(ros_map)
    grid = grid_for(free, ros_map.resolution)
    cells = _ok_cells(grid)
    if len(cells) < 2:
        return ros_map, free, grid, None
    start, goal = draw(st.sampled_from(cells)), draw(st.sampled_from(cells))
    return ros_map, free, grid, plan(grid, start, goal)


@settings(max_examples=150, deadline=None)
@given(floors(), st.floats(0.0, 3.0))
def test_routes_kept_to_the_side_on_random_floors_stay_on_ok_cells(case, offset_m) -> None:
    ros_map, free, grid, planned = case
    if planned is None:
        return  # racks left no free cell
    route = keep_to_side(grid, planned, offset_m / ros_map.resolution)
    _assert_on_ok_cells(grid, free, planned, route)


@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 12),
    st.tuples(*[st.floats(0.0, 200.0, allow_nan=False)] * 4),
)
def test_a_segment_passes_over_the_cells_it_names(cell_px, ends) -> None:
    """`segment_cells` names every cell a point of the segment lies in, one step apart."""
    a, b = ends[:2], ends[2:]
    named = segment_cells(cell_px, a, b)
    n = max(1, math.ceil(math.dist(a, b) * 20))
    for k in range(n + 1):
        t = k / n
        u, v = a[0] * (1 - t) + b[0] * t, a[1] * (1 - t) + b[1] * t
        # the sample's own rounding may put it a hair across a cell's edge
        near = {
            (int((v + dv) // cell_px), int((u + du) // cell_px))
            for du in (-1e-9, 0.0, 1e-9)
            for dv in (-1e-9, 0.0, 1e-9)
        }
        assert near & set(named), (u, v)
    assert all(
        max(abs(p[0] - q[0]), abs(p[1] - q[1])) == 1 for p, q in zip(named, named[1:], strict=False)
    )


def _aisle() -> RosMap:
    """A 20 m x 4 m aisle between racks, at 5 cm a pixel."""
    pixels = np.zeros((120, 440), dtype=np.uint8)
    pixels[20:100, 20:420] = 254
    return RosMap(pixels, 0.05, (0.0, 0.0, 0.0))


def _walk(route, step_px: float = 0.5) -> np.ndarray:
    """The route's points every `step_px`."""
    points = []
    for (u0, v0), (u1, v1) in zip(route, route[1:], strict=False):
        n = max(1, math.ceil(math.hypot(u1 - u0, v1 - v0) / step_px))
        points += [(u0 + (u1 - u0) * k / n, v0 + (v1 - v0) * k / n) for k in range(n)]
    return np.asarray(points)


@pytest.mark.parametrize("offset_m,passes_clear", [(0.0, False), (0.6, True), (1.2, True)])
def test_robots_meeting_head_on_in_an_aisle_pass_apart(offset_m, passes_clear) -> None:
    """Down the middle both routes are one line; kept to the side they run two offsets
    apart in the aisle's middle, where the robots meet away from the stations at its ends
    (the closest points of the two routes: a bound on how close the robots come)."""
    ros_map = _aisle()
    grid = grid_for(drivable(ros_map), ros_map.resolution)
    west, east = grid.cell_at(40, 60), grid.cell_at(400, 60)
    there, back = plan(grid, west, east), plan(grid, east, west)
    assert there is not None and back is not None
    offset_px = offset_m / ros_map.resolution
    going, coming = (
        points[(points[:, 0] >= 120) & (points[:, 0] <= 320)]
        for points in (
            _walk(keep_to_side(grid, there, offset_px)),
            _walk(keep_to_side(grid, back, offset_px)),
        )
    )
    gaps = np.hypot(going[:, None, 0] - coming[None, :, 0], going[:, None, 1] - coming[None, :, 1])
    apart_m = float(gaps.min()) * ros_map.resolution
    assert (apart_m > NEAR_MISS_M) is passes_clear, apart_m
    assert apart_m == pytest.approx(2 * offset_m, abs=0.05)
