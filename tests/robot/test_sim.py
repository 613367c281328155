"""The simulator's step function: robots on free cells, collision-free paths, batteries,
loads, map changes as chunks, and the faults it can inject (no broker)."""

from __future__ import annotations

import math
from dataclasses import replace

import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.adapters.ros_map import RosMap, drivable, load_ros_map
from mapservice.core.wire2019 import (
    Limits,
    Rejection,
    decode_chunk_create,
    decode_coordinates,
    parse_timestamp,
)
from mapservice.robot import sim
from mapservice.robot.chunks import chunk_pixels, metres_to_pixel
from mapservice.robot.faults import Faults, robot_skew_ms, to_messages
from mapservice.robot.planning import build_grid, dilate, path_is_clear, plan, simplify
from mapservice.robot.sim import SimConfig, _protected, new_state, step
from tests.fixtures.paths import MAPS

T0 = 1_795_255_200_000


def pixel_point(state, x, y):
    """Continuous image point of a world point (inverse of sim.to_metres, up to rounding)."""
    res, (ox, oy, _) = state.meta.resolution, state.meta.origin
    return (x - ox) / res, state.meta.height - (y - oy) / res


def run(state, steps):
    for _ in range(steps):
        state, out = step(state)
        yield state, out


@pytest.mark.parametrize(
    "name,robots,steps",
    [("depot", 6, 600), ("warehouse", 4, 200), ("tb3_sandbox", 5, 300), ("map_circular", 5, 300)],
)
def test_robots_stay_on_free_cells_and_publish_clear_paths(name, robots, steps) -> None:
    """Over many steps with map changes, every pose is on a drivable pixel of the map as it
    is then, and every published path crosses only drivable pixels."""
    state = new_state(
        load_ros_map(MAPS / f"{name}.yaml"),
        robots,
        seed=3,
        t_ms=T0,
        config=SimConfig(change_every_s=8),
    )
    changes = paths = 0
    for state, out in run(state, steps):
        free = drivable(state.ros_map)  # the current map, after this step's change
        assert len(out.poses) == robots
        changes += len(out.notes)
        for pose in out.poses:
            col, row = metres_to_pixel(pose.x, pose.y, state.meta)
            assert free[row, col], (
                f"{pose.robot_id} stands on a blocked pixel at {pose.x}, {pose.y}"
            )
            if pose.path:
                paths += 1
                pts = [pixel_point(state, x, y) for x, y in pose.path]
                assert path_is_clear(pts, free), f"{pose.robot_id}'s path crosses an obstacle"
                assert math.dist(pts[0], pixel_point(state, pose.x, pose.y)) < 0.5
    assert changes >= 3 and paths > steps


def test_small_nav2_maps_plan_on_finer_cells_than_big_maps() -> None:
    """nav2's 384 x 384 px sandbox gets a planning cell below 0.25 m; the warehouse keeps
    the coarse one (fast planning)."""
    small = new_state(load_ros_map(MAPS / "tb3_sandbox.yaml"), 5, seed=1, t_ms=T0)
    big = new_state(load_ros_map(MAPS / "warehouse.yaml"), 5, seed=1, t_ms=T0)
    assert small.config.cell_m < 0.25 and len(small.robots) == 5
    assert big.config.cell_m == pytest.approx(0.24)


def test_a_map_too_small_for_n_robots_runs_fewer() -> None:
    """Asking for more robots than the sandbox's free area hosts runs as many as fit
    (each on a cell of its own), not a crash and not robots stacked on one cell."""
    state = new_state(load_ros_map(MAPS / "tb3_sandbox.yaml"), 500, seed=1, t_ms=T0)
    assert 5 <= len(state.robots) < 500
    starts = [r.pos for r in state.robots]
    assert len(set(starts)) == len(starts)


def test_a_map_without_room_says_so() -> None:
    """A map with almost no free space raises a message naming what is missing."""
    pixels = np.zeros((40, 40), dtype=np.uint8)
    pixels[18:22, 18:22] = 254
    tiny = RosMap(pixels=pixels, resolution=0.05, origin=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"too little free space.*planning cells"):
        new_state(tiny, 1, seed=1, t_ms=T0)


def test_map_changes_are_published_as_the_chunks_they_touched() -> None:
    """Each change's chunks hold exactly the current map's pixels of those chunks, and the
    chunks no change touched stay as they were."""
    base = load_ros_map(MAPS / "depot.yaml")
    state = new_state(base, 3, seed=5, t_ms=T0, config=SimConfig(change_every_s=5))
    touched: set[tuple[int, int]] = set()
    kinds = set()
    for state, out in run(state, 400):
        for chunk in out.chunks:
            touched.add((chunk.row, chunk.column))
            assert chunk.pixels == chunk_pixels(
                state.ros_map.pixels, state.meta, chunk.row, chunk.column, 205
            )
            assert chunk.robot_id in {r.robot_id for r in state.robots}
        kinds.update(n.split(" ")[0] + " " + n.split(" ")[1] for n in out.notes)
    assert touched and {"pallet appeared", "pallet taken"} <= kinds
    diff = np.argwhere(state.ros_map.pixels != base.pixels)
    assert {(int(r) // 100, int(c) // 100) for r, c in diff} <= touched


def test_batteries_drain_and_recharge_and_loads_are_carried() -> None:
    """With a fast drain robots go to a charger, charge there (charging=True) and carry loads
    between stations (loaded toggles)."""
    config = SimConfig(change_every_s=0, drain_per_s=2.0, charge_per_s=10.0, dwell_s=2)
    state = new_state(load_ros_map(MAPS / "depot.yaml"), 3, seed=11, t_ms=T0, config=config)
    chargers = {state.grid.centre_px(c) for c in state.chargers}
    charged = loaded_changes = 0
    last_loaded = {r.robot_id: r.loaded for r in state.robots}
    for state, out in run(state, 400):
        for robot, pose in zip(state.robots, out.poses):
            assert 0.0 <= pose.battery <= 100.0
            if pose.charging:
                charged += 1
                assert robot.pos in chargers
            if pose.loaded != last_loaded[robot.robot_id]:
                loaded_changes += 1
                last_loaded[robot.robot_id] = pose.loaded
    assert charged > 0 and loaded_changes >= 3


def test_step_is_deterministic() -> None:
    """The same map, seed and start give the same outputs (a pure function of the state)."""
    m = load_ros_map(MAPS / "depot.yaml")
    a = new_state(m, 2, seed=9, t_ms=T0, config=SimConfig(change_every_s=4))
    b = new_state(m, 2, seed=9, t_ms=T0, config=SimConfig(change_every_s=4))
    outs_a = [out for _, out in run(a, 60)]
    outs_b = [out for _, out in run(b, 60)]
    assert outs_a == outs_b


def test_planner_avoids_walls_on_a_tiny_map() -> None:
    """A* goes round a wall through the gap, and no path exists once the gap is closed."""
    free = np.ones((40, 40), dtype=bool)
    free[:, 19:21] = False
    free[26:36, 19:21] = True  # the gap
    grid = build_grid(free, cell_px=2, inflate=1)
    cells = plan(grid, (2, 2), (2, 17))
    assert cells is not None and any(r >= 14 for r, _ in cells)
    assert path_is_clear([grid.centre_px(c) for c in simplify(cells)], free)
    free[26:36, 19:21] = False
    assert plan(build_grid(free, 2, 1), (2, 2), (2, 17)) is None
    assert dilate(np.eye(3, dtype=bool), 0).tolist() == np.eye(3, dtype=bool).tolist()


def test_faults_loss_skew_and_bad_input() -> None:
    """Loss drops messages, clock skew shifts a robot's timestamps by a fixed amount, and
    every injected bad message is rejected by the gateway's decoder."""
    state = new_state(load_ros_map(MAPS / "depot.yaml"), 5, seed=1, t_ms=T0)
    state, out = step(state)
    clean, lost = to_messages(out)
    assert lost == 0 and len(clean) == 5 and {m.kind for m in clean} == {"pose"}
    _, lost = to_messages(out, Faults(loss=1.0))
    assert lost == 5
    skewed, _ = to_messages(out, Faults(clock_skew_s=30), seed=2)
    for msg, pose in zip(skewed, out.poses):
        ts = parse_timestamp(msgspec.json.decode(msg.payload)["timestamp"])
        assert ts - pose.t_ms == robot_skew_ms(pose.robot_id, Faults(clock_skew_s=30), 2) != 0
        assert abs(ts - pose.t_ms) <= 30_000
    limits = Limits(chunk_rows=state.meta.chunk_rows, chunk_cols=state.meta.chunk_cols)
    reasons = set()
    for tick in range(40):
        bad, _ = to_messages(out, Faults(bad_rate=1.0), tick=tick)
        for msg in bad:
            assert msg.kind.startswith("bad:")
            if msg.topic == "iot/chunks/create":
                result = decode_chunk_create(msg.payload, T0 + 1000, limits)
            else:
                result = decode_coordinates(
                    msg.topic.rsplit("/", 1)[1], msg.payload, T0 + 1000, limits
                )
            assert isinstance(result, Rejection), msg.kind
            assert result.reason.value == msg.kind[4:]
            reasons.add(result.reason.value)
    assert len(reasons) >= 5
    for msg in clean:
        assert not isinstance(
            decode_coordinates(msg.topic.rsplit("/", 1)[1], msg.payload, T0 + 1000, limits),
            Rejection,
        )


def test_paths_fit_the_gateway_limit() -> None:
    """A published path never exceeds the gateway's 1,000-point limit."""
    state = new_state(
        load_ros_map(MAPS / "warehouse.yaml"),
        3,
        seed=2,
        t_ms=T0,
        config=replace(SimConfig(), change_every_s=0),
    )
    for _state, out in run(state, 30):
        assert all(len(p.path) <= 1000 for p in out.poses)


def test_new_obstacles_keep_off_the_stretch_a_robot_drives_next() -> None:
    """The whole segment from a robot to its next waypoint is protected from map changes,
    not only its two ends (a replan keeps that waypoint, so an obstacle there would stay
    on the published path)."""
    state = new_state(
        load_ros_map(MAPS / "warehouse.yaml"),
        1,
        seed=3,
        t_ms=T0,
        config=replace(SimConfig(), change_every_s=0),
    )
    g = state.grid
    a = g.centre_px((5, 5))
    b = g.centre_px((5, 5 + 20))
    robot = replace(state.robots[0], pos=a, waypoints=(b,))
    mask = _protected(replace(state, robots=(robot,)))
    assert all(mask[g.cell_at(*g.centre_px((5, col)))] for col in range(5, 26))


@st.composite
def floors(draw):
    """A walled floor of odd size with random racks (occupied rectangles) in it."""
    height, width = draw(st.integers(121, 181)), draw(st.integers(121, 241))
    pixels = np.full((height, width), 254, dtype=np.uint8)
    pixels[:3, :] = pixels[-3:, :] = pixels[:, :3] = pixels[:, -3:] = 0
    for _ in range(draw(st.integers(0, 6))):
        r, c = draw(st.integers(0, height - 1)), draw(st.integers(0, width - 1))
        pixels[r : r + draw(st.integers(3, 40)), c : c + draw(st.integers(3, 40))] = 0
    return RosMap(pixels, 0.05, (-1.0, 2.0, 0.0)), draw(st.integers(0, 10_000))


@settings(max_examples=8, deadline=None)
@given(floors())
def test_generated_floors_keep_robots_off_obstacles(case) -> None:
    """On random floors (with map changes every few seconds) no pose is ever on a blocked
    pixel and no published path crosses one."""
    ros_map, seed = case
    config = SimConfig(change_every_s=3, stations=3, chargers=1)
    try:
        state = new_state(ros_map, 3, seed=seed, t_ms=T0, config=config)
    except ValueError:
        return  # racks left too little free space for stations: nothing to simulate
    for state, out in run(state, 120):
        free = drivable(state.ros_map)
        for pose in out.poses:
            col, row = metres_to_pixel(pose.x, pose.y, state.meta)
            assert free[row, col]
            if pose.path:
                assert path_is_clear([pixel_point(state, x, y) for x, y in pose.path], free)


def test_a_floor_change_across_a_cached_route_makes_the_robot_replan() -> None:
    """Routes are cached per (start, goal) and reused without a check while the floor stays
    as it is; after a change that blocks a cached route, the same trip plans around the new
    obstacle, while a cached route the change left clear is still reused."""
    state = new_state(
        load_ros_map(MAPS / "warehouse.yaml"),
        1,
        seed=3,
        t_ms=T0,
        config=replace(SimConfig(), change_every_s=0),
    )
    g = state.grid
    robot = replace(state.robots[0], pos=g.centre_px(state.stations[0]), waypoints=())
    far, near = state.stations[1], state.stations[2]
    first = sim._route(state, robot, far)
    other = sim._route(state, robot, near)
    assert first is not None and other is not None
    assert sim._route(state, robot, far) is first  # reused as it was

    # A pallet on a cell in the middle of the cached route, away from the other route.
    cells = state.routes[(g.cell_at(*robot.pos), far)].cells
    other_cells = set(state.routes[(g.cell_at(*robot.pos), near)].cells)
    row, col = next(
        c
        for c in cells[len(cells) // 3 :]
        if all(abs(c[0] - o[0]) > 4 or abs(c[1] - o[1]) > 4 for o in other_cells)
    )
    pixels = state.ros_map.pixels.copy()
    pixels[row * g.cell_px : (row + 1) * g.cell_px, col * g.cell_px : (col + 1) * g.cell_px] = 0
    changed = sim._with_pixels(state, pixels)
    free = drivable(changed.ros_map)
    assert not path_is_clear(list(first), free)

    again = sim._route(changed, robot, far)
    assert again is not None and again != first
    assert path_is_clear(list(again), free)
    assert sim._route(changed, robot, near) is other  # still clear: kept, not planned again
