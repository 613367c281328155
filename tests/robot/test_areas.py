"""Which advertisement areas a robot reads (robot/areas.py): those of the map's chunks with a
pixel in the square of its position plus the margin, checked against an enumeration of
every pixel of generated maps (origins on either side of 0, several resolutions and chunk
sizes, positions on and off the map and on pixel, chunk and area edges); and an agent's
subscriptions at a real Mosquitto follow it as it moves."""

from __future__ import annotations

import queue
import random
import time
from dataclasses import dataclass

import msgspec
import numpy as np
import pytest

from mapservice.adapters.mqtt_client import make_client
from mapservice.core.areas import AreaGrid, area_topic
from mapservice.core.events import MapMetaSet
from mapservice.robot.areas import (
    areas_around,
    areas_around_pixel,
    map_areas,
)
from tests.fixtures.mosquitto import mosquitto  # noqa: F401 (a fixture)

# Resolutions, origins and offsets that binary floating point holds exactly, so the
# enumeration's interval tests and the code's arithmetic agree on every edge.
RESOLUTIONS = (0.25, 0.5, 1.0, 0.125)


def random_meta(rng: random.Random) -> MapMetaSet:
    width, height = rng.randint(1, 40), rng.randint(1, 40)
    cw, ch = rng.randint(1, 9), rng.randint(1, 9)
    res = rng.choice(RESOLUTIONS)
    origin = (rng.randint(-40, 40) * 0.25, rng.randint(-40, 40) * 0.25, 0.0)
    return MapMetaSet(
        width, height, cw, ch, -(-height // ch), -(-width // cw), resolution=res, origin=origin
    )


def by_enumeration(
    x: float, y: float, margin: float, meta: MapMetaSet, grid: AreaGrid
) -> frozenset:
    """Every pixel of the map whose square (x0 <= x < x0 + res, the same for y; row 0 at
    the top) meets the closed square [x - m, x + m] x [y - m, y + m]: its chunk's area."""
    res, (ox, oy, _) = meta.resolution, meta.origin
    assert res is not None
    cols = np.arange(meta.width)
    rows = np.arange(meta.height)
    x0 = ox + cols * res
    y0 = oy + (meta.height - 1 - rows) * res
    col_hit = (x0 <= x + margin) & (x0 + res > x - margin)
    row_hit = (y0 <= y + margin) & (y0 + res > y - margin)
    return frozenset(
        grid.area_of_chunk(int(r) // meta.chunk_height, int(c) // meta.chunk_width)
        for r in rows[row_hit]
        for c in cols[col_hit]
    )


def edgy_coordinate(rng: random.Random, origin: float, res: float, size: int, step: int) -> float:
    """Mostly on the map, sometimes beyond it; often exactly on a pixel's, a chunk's or an
    area's edge (`step` pixels apart)."""
    if rng.random() < 0.5:
        return origin + rng.randint(0, size // step) * step * res
    return origin + rng.randint(-size // 2, 5 * size) * res / 4


def test_a_robot_reads_the_areas_its_surroundings_touch() -> None:
    rng = random.Random(17)
    off_map = 0
    for _ in range(600):
        meta = random_meta(rng)
        grid = AreaGrid(rng.randint(1, 4))
        res, (ox, oy, _) = meta.resolution, meta.origin
        assert res is not None
        x = edgy_coordinate(rng, ox, res, meta.width, meta.chunk_width * grid.chunks)
        y = edgy_coordinate(rng, oy, res, meta.height, meta.chunk_height * grid.chunks)
        margin = rng.choice([0.0, res, res / 2, rng.randint(0, 20) * res / 4])
        expected = by_enumeration(x, y, margin, meta, grid)
        assert areas_around(x, y, margin, meta, grid) == expected, (meta, grid, x, y, margin)
        off_map += not expected
    assert 30 < off_map < 300  # both kinds of case were drawn


def test_the_simulators_pixel_coordinates_give_the_areas_of_the_pixels_they_touch() -> None:
    rng = random.Random(23)
    for _ in range(400):
        meta = random_meta(rng)
        grid = AreaGrid(rng.randint(1, 4))
        u = rng.randint(-8, 4 * meta.width + 8) / 4
        v = rng.randint(-8, 4 * meta.height + 8) / 4
        m = rng.randint(0, 40) / 4
        expected = frozenset(
            grid.area_of_chunk(r // meta.chunk_height, c // meta.chunk_width)
            for r in range(meta.height)
            for c in range(meta.width)
            if c <= u + m and c + 1 > u - m and r <= v + m and r + 1 > v - m
        )
        # A window ending exactly on a pixel's edge also takes that pixel: never fewer.
        got = areas_around_pixel(u, v, m, meta, grid)
        assert got >= expected and len(got - expected) <= 2 * (grid.chunks + 1)


def test_before_it_knows_where_it_is_a_robot_reads_every_area_of_the_map() -> None:
    rng = random.Random(29)
    for _ in range(200):
        meta = random_meta(rng)
        grid = AreaGrid(rng.randint(1, 4))
        expected = {
            grid.area_of_chunk(r, c) for r in range(meta.chunk_rows) for c in range(meta.chunk_cols)
        }
        assert map_areas(meta, grid) == expected


def test_a_margin_is_zero_or_more() -> None:
    meta = MapMetaSet(10, 10, 5, 5, 2, 2, resolution=1.0, origin=(0.0, 0.0, 0.0))
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="0 or more"):
            areas_around(1.0, 1.0, bad, meta, AreaGrid(1))


# --- an agent at a real broker ------------------------------------------------------------


@dataclass
class ScriptedPose:
    """A pose source that is where the test puts it."""

    x: float
    y: float

    def read(self):
        from mapservice.robot.pose_sources import PoseReading

        return PoseReading(self.x, self.y, (0.0, 0.0, 0.0, 1.0))


def publish_everywhere(port: int, grid: AreaGrid, meta: MapMetaSet, tag: str) -> None:
    """One advertisement on every area's topic of the map, as the processors would send."""
    client = make_client(f"area-pub-{time.time_ns()}")
    client.connect("127.0.0.1", port)
    client.loop_start()
    try:
        for area in sorted(map_areas(meta, grid)):
            payload = msgspec.json.encode({"area": list(area), "tag": tag, "robotId": "other"})
            info = client.publish(area_topic("iot/chunks/advertisement", area), payload, qos=1)
            info.wait_for_publish(10)
    finally:
        client.loop_stop()
        client.disconnect()


def drain(q: queue.Queue, tag: str, settle_s: float = 1.0) -> set[tuple[int, int]]:
    got: set[tuple[int, int]] = set()
    deadline = time.monotonic() + settle_s
    while time.monotonic() < deadline:
        try:
            doc = msgspec.json.decode(q.get(timeout=0.05))
        except queue.Empty:
            continue
        if doc["tag"] == tag:
            got.add(tuple(doc["area"]))
    return got


def until_subscribed(agent, areas: frozenset) -> None:
    """SUBACKs are asynchronous: wait until the feed holds the set (sent on the wire)."""
    deadline = time.monotonic() + 10
    while agent.area_feed.needed.current() != areas and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)  # the broker has the SUBSCRIBE and UNSUBSCRIBE packets before the test's


def test_the_agents_subscriptions_follow_it(tmp_path, mosquitto) -> None:  # noqa: F811
    """An agent reads every area of its map until its first pose, then only the areas
    around it; as it drives across the map it reads the new areas and no longer the ones
    it left. Its 2019 mode reads nothing on the area topics (it reads the 2019 topic)."""
    from mapservice.robot.agent import RobotAgent
    from tests.robot.test_agent import robot_copy

    port = mosquitto
    grid = AreaGrid(1)  # the depot map: 4 x 7 chunks of 5 m, an area a chunk
    pose = ScriptedPose(0.0, 0.0)
    agent = RobotAgent(
        robot_copy(tmp_path, "agv-1"),
        "agv-1",
        "http://unused",
        f"mqtt://127.0.0.1:{port}",
        pose_source=pose,
        area_grid=grid,
        area_margin_m=1.0,
    )
    meta = agent.local.meta
    res, (ox, oy, _) = meta.resolution, meta.origin
    assert res is not None
    agent.connect()
    try:
        until_subscribed(agent, map_areas(meta, grid))
        publish_everywhere(port, grid, meta, "before")
        assert drain(agent.adverts, "before") == set(map_areas(meta, grid))
        # Walk along the map's second row of chunks, stopping in each whole chunk's middle
        # and on each edge after it (the last one the map's edge in the partial chunk 6).
        chunk_m = meta.chunk_width * res
        y = oy + (meta.height - 1.5 * meta.chunk_height) * res  # chunk row 1's middle
        visited = 0
        for step in range(2 * (meta.width // meta.chunk_width)):
            pose.x, pose.y = ox + (step + 1) * chunk_m / 2, y
            assert agent.publish_pose()
            expected = areas_around(pose.x, pose.y, 1.0, meta, grid)
            assert len(expected) == (1 if step % 2 == 0 else 2)
            until_subscribed(agent, expected)
            publish_everywhere(port, grid, meta, f"step-{step}")
            assert drain(agent.adverts, f"step-{step}") == set(expected), (step, pose)
            visited += 1
        assert visited == 12
    finally:
        agent.client.loop_stop()
        agent.client.disconnect()


def test_an_agent_speaking_2019_reads_the_2019_topic_only(tmp_path, mosquitto) -> None:  # noqa: F811
    from mapservice.robot.agent import RobotAgent
    from tests.robot.test_agent import robot_copy

    port = mosquitto
    agent = RobotAgent(
        robot_copy(tmp_path, "old-1"),
        "old-1",
        "http://unused",
        f"mqtt://127.0.0.1:{port}",
        pose_source=ScriptedPose(1.0, 1.0),
        advertisements="2019",
        area_grid=AreaGrid(1),
    )
    agent.connect()
    try:
        assert agent.area_feed is None
        deadline = time.monotonic() + 10
        while not agent.client.is_connected() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert agent.publish_pose()  # wherever it is, it reads the whole plant
        time.sleep(0.3)  # its SUBSCRIBE is at the broker before the test's messages
        publish_everywhere(port, AreaGrid(1), agent.local.meta, "areas")
        client = make_client(f"plant-pub-{time.time_ns()}")
        client.connect("127.0.0.1", port)
        client.loop_start()
        for area in ((0, 0), (3, 6)):
            payload = msgspec.json.encode({"area": list(area), "tag": "2019", "robotId": "x"})
            client.publish("iot/chunks/advertisement", payload, qos=1).wait_for_publish(10)
        client.loop_stop()
        client.disconnect()
        got = [msgspec.json.decode(p) for p in drain_raw(agent.adverts)]
        assert [(d["tag"], d["area"]) for d in got] == [("2019", [0, 0]), ("2019", [3, 6])]
    finally:
        agent.client.loop_stop()
        agent.client.disconnect()


def drain_raw(q: queue.Queue, settle_s: float = 1.0) -> list[bytes]:
    out: list[bytes] = []
    deadline = time.monotonic() + settle_s
    while time.monotonic() < deadline:
        try:
            out.append(q.get(timeout=0.05))
        except queue.Empty:
            continue
    return out


def test_an_unknown_advertisement_mode_is_refused(tmp_path) -> None:
    from mapservice.robot.agent import RobotAgent
    from tests.robot.test_agent import robot_copy

    with pytest.raises(ValueError, match="advertisements"):
        RobotAgent(
            robot_copy(tmp_path, "r"),
            "r",
            "http://unused",
            "mqtt://127.0.0.1:1",
            advertisements="all",
        )
