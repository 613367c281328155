"""The simulator's shortcuts compute what the plain computation does: `evolve` is
`dataclasses.replace`, a floor change reclassifies only its patch yet leaves the drivable
mask and the planning grid the whole map gives, `to_metres` is `pixel_to_metres` rounded,
and the A* heuristic table holds the octile distances the search used to compute."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.adapters.ros_map import drivable, load_ros_map
from mapservice.robot import sim
from mapservice.robot.chunks import pixel_to_metres
from mapservice.robot.planning import _octile_heuristic
from mapservice.robot.sim import Robot, SimConfig, new_state, step
from mapservice.robot.sim_model import evolve
from mapservice.robot.sim_zones import plan_grids
from tests.fixtures.paths import MAPS

T0 = 1_795_255_200_000

changes = st.fixed_dictionaries(
    {},
    optional={
        "pos": st.tuples(st.floats(0, 500), st.floats(0, 500)),
        "yaw": st.floats(-math.pi, math.pi),
        "battery": st.floats(0, 100),
        "waypoints": st.lists(st.tuples(st.floats(0, 500), st.floats(0, 500))).map(tuple),
        "task": st.sampled_from(["idle", "to_pick", "charging"]),
        "target": st.integers(-1, 9),
        "loaded": st.booleans(),
        "wait_s": st.floats(-10, 10),
        "charging": st.booleans(),
    },
)


@given(changes)
def test_evolve_is_replace(fields) -> None:
    robot = Robot("sim-000", (1.0, 2.0), 0.5, 80.0, waypoints=((3.0, 4.0),))
    evolved = evolve(robot, **fields)
    assert evolved == replace(robot, **fields)
    assert robot == Robot("sim-000", (1.0, 2.0), 0.5, 80.0, waypoints=((3.0, 4.0),))


def test_evolve_refuses_a_field_the_record_lacks() -> None:
    robot = Robot("sim-000", (1.0, 2.0), 0.5, 80.0)
    with pytest.raises(TypeError, match="speed"):
        evolve(robot, speed=2.0)


@pytest.mark.parametrize("name", ["warehouse.yaml", "tb3_sandbox.yaml"])
@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_after_every_floor_change_the_masks_are_the_whole_maps(name, seed) -> None:
    ros_map = load_ros_map(MAPS / name)
    state = new_state(ros_map, 3, seed=seed, t_ms=T0, config=SimConfig(dt_s=5, change_every_s=20))
    changed = 0
    for _ in range(120):
        before = state.ros_map
        state, _ = step(state)
        if state.ros_map is not before:
            changed += 1
            assert np.array_equal(state.drivable, drivable(state.ros_map))
            grid, _ = plan_grids(
                drivable(state.ros_map), state.zones, ros_map.resolution, state.config
            )
            assert np.array_equal(state.grid.ok, grid.ok)
    assert changed > 0


@given(
    st.tuples(st.floats(-50, 2000, allow_nan=False), st.floats(-50, 2000, allow_nan=False)),
    st.sampled_from(["warehouse.yaml", "tb3_sandbox.yaml", "depot.yaml"]),
)
def test_to_metres_is_pixel_to_metres_rounded(point, name) -> None:
    state = _states(name)
    x, y = pixel_to_metres(point[0] - 0.5, point[1] - 0.5, state.meta)
    assert sim.to_metres(state, point) == (round(x, 3), round(y, 3))


@given(
    st.integers(3, 40).flatmap(
        lambda w: st.tuples(st.just(w), st.integers(3, 40), st.integers(0, 10_000))
    )
)
def test_the_heuristic_table_holds_the_octile_distances(shape) -> None:
    width, height, pick = shape
    size = width * height
    target = pick % size
    table = _octile_heuristic(size, width, target)
    tr, tc = divmod(target, width)
    for node in range(size):
        r, c = divmod(node, width)
        dr, dc = abs(r - tr), abs(c - tc)
        assert table[node] == (dr + dc) + (math.sqrt(2.0) - 2) * (dr if dr < dc else dc)


_STATES: dict = {}


def _states(name: str):
    if name not in _STATES:
        _STATES[name] = new_state(load_ros_map(MAPS / name), 1, seed=3, t_ms=T0)
    return _STATES[name]
