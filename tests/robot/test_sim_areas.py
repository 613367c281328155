"""The simulator's robots read the advertisement areas around them, each on its own
connection under its own credential (a real Mosquitto checking identities and the ACL):
as the shift moves them, every robot's connection is subscribed to exactly the areas
around where it is, and receives the changes of those areas and of no other."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

from mapservice.adapters.mqtt_auth import PROCESSORS_USER
from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.areas import AreaGrid, area_topic, area_topic_filter
from mapservice.robot.areas import areas_around_pixel, map_areas
from mapservice.robot.connection import RobotClients, RobotMqtt
from mapservice.robot.sim import SimConfig, sim_robot_id, step
from mapservice.robot.simrun import SimRunner
from tests.fixtures.paths import MAPS
from tests.robot.test_sim_identity import ServiceClient, wait_until

ADS = "iot/chunks/advertisement"
MARGIN_M = 2.0


def test_each_simulated_robot_reads_the_areas_around_it_as_it_moves(mosquitto_identities):
    broker = mosquitto_identities
    robots = [sim_robot_id("area", i) for i in range(3)]
    credentials = {r: broker.files.add_robot(r).password for r in robots}
    broker.start()
    grid = AreaGrid(1)  # the depot map: 4 x 7 chunks of 5 m, an area a chunk
    runner = SimRunner(
        broker.url,
        load_ros_map(MAPS / "depot.yaml"),
        len(robots),
        prefix="area",
        config=SimConfig(change_every_s=0, dwell_s=0.5),
        mqtt_conn=RobotMqtt(broker.url, credentials),
        advertisement_topic=ADS,
        area_grid=grid,
        area_margin_m=MARGIN_M,
    )
    meta = runner.state.meta
    margin_px = MARGIN_M / meta.resolution
    clients = RobotClients(runner.conn, robots, "area-test")
    clients.connect()
    processors = ServiceClient(broker, PROCESSORS_USER)
    received: dict[str, list[str]] = defaultdict(list)
    lock = threading.Lock()
    try:
        runner._read_areas(clients)
        runner.follow_robots()
        first = {
            r.robot_id: runner.area_feeds[r.robot_id].needed.current() for r in runner.state.robots
        }
        time.sleep(0.5)  # the SUBSCRIBEs are at the broker
        # The runner counts what its robots read: each robot its own areas' messages.
        for area in sorted(map_areas(meta, grid)):
            processors.publish(area_topic(ADS, area), {"area": list(area)})
        expected_total = sum(len(a) for a in first.values())
        assert wait_until(lambda: runner.stats.advertisements >= expected_total, 10)
        time.sleep(0.3)
        assert runner.stats.advertisements == expected_total
        # From here each connection's messages are recorded by topic.
        for robot_id, client in clients.clients.items():

            def record(_c, _u, msg, robot_id=robot_id) -> None:
                with lock:
                    received[str(robot_id)].append(msg.topic)

            client.message_callback_add(area_topic_filter(ADS), record)
        moved = 0
        for tick in range(4):
            for _ in range(5):
                runner.state, _out = step(runner.state)
            runner.follow_robots()
            expected = {
                r.robot_id: areas_around_pixel(*r.pos, margin_px, meta, grid)
                for r in runner.state.robots
            }
            moved += sum(expected[r] != first[r] for r in robots)
            for robot_id, areas in expected.items():
                assert runner.area_feeds[robot_id].needed.current() == areas
                assert 1 <= len(areas) <= 4
            time.sleep(0.5)  # the UNSUBSCRIBEs and SUBSCRIBEs are at the broker
            with lock:
                received.clear()
            for area in sorted(map_areas(meta, grid)):
                processors.publish(area_topic(ADS, area), {"tick": tick})
            want = {r: sorted(area_topic(ADS, a) for a in expected[r]) for r in robots}
            assert wait_until(
                lambda want=want: all(len(received[r]) >= len(want[r]) for r in robots), 10
            )
            time.sleep(0.3)  # nothing beyond
            with lock:
                assert {r: sorted(received[r]) for r in robots} == want, tick
        assert moved > 0, "no robot left the areas it started in; the test proves nothing"
        assert "not authorised" not in broker.log().lower()
    finally:
        clients.close()
        processors.close()
