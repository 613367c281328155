"""`mapservice bench fanout` counts the messages of a simulated shift's map changes: one
area over the whole map sends what the 2019 topic sends; areas of one chunk with no margin
send each change to exactly the robots standing in its chunk (counted here by replaying the
same shift)."""

from __future__ import annotations

import math

from mapservice.adapters.ros_map import load_ros_map
from mapservice.bench.fanout import run
from mapservice.core.areas import AreaGrid
from mapservice.robot.sim import SimConfig, new_state, step
from tests.fixtures.paths import MAPS

DEPOT = MAPS / "depot.yaml"  # 4 x 7 chunks


def test_one_area_over_the_whole_map_sends_what_the_2019_topic_sends() -> None:
    r = run(DEPOT, 4, 120, grid=AreaGrid(7), margin_m=3.0, change_every_s=5.0)
    assert r.changes > 0 and r.robots == 4
    assert r.sent_areas == r.sent_2019 == r.changes * 4
    assert r.max_readers == 4 and r.areas_read_mean == 1.0 and r.ratio == 1.0
    assert r.advertisement_bytes_mean > 500  # base64 chunk + PNG + the 2019 fields


def test_areas_of_a_chunk_send_each_change_to_the_robots_in_its_chunk() -> None:
    robots, seconds = 6, 150
    r = run(DEPOT, robots, seconds, grid=AreaGrid(1), margin_m=0.0, change_every_s=5.0, seed=3)
    state = new_state(load_ros_map(DEPOT), robots, seed=3, config=SimConfig(change_every_s=5.0))
    meta = state.meta
    changes = in_chunk = 0
    for _ in range(seconds):
        state, out = step(state)
        cells = [
            (math.floor(v) // meta.chunk_height, math.floor(u) // meta.chunk_width)
            for u, v in (robot.pos for robot in state.robots)
        ]
        for chunk in out.chunks:
            changes += 1
            in_chunk += cells.count((chunk.row, chunk.column))
    assert r.changes == changes > 5
    assert r.sent_areas == in_chunk < r.sent_2019 == changes * robots
    assert r.areas_read_mean == 1.0  # no margin: the one chunk a robot stands in
