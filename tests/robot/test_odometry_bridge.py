"""The agent's ROS-bridge pose source against a real Mosquitto: odometry JSON on a local
topic becomes the robot's 2019 pose, stamped with the current time."""

from __future__ import annotations

import time

import msgspec
import pytest

from mapservice.adapters.mqtt_client import make_client
from mapservice.core.wire2019 import parse_timestamp
from mapservice.robot.agent import RobotAgent
from mapservice.robot.pose_sources import OdometryPose
from tests.fixtures.paths import MAPS

pytestmark = pytest.mark.integration


class CapturingClient:
    def __init__(self) -> None:
        self.published: list[tuple[str, bytes]] = []

    def publish(self, topic, payload, qos=0):
        self.published.append((topic, payload))


def test_odometry_topic_becomes_the_robots_pose(mosquitto) -> None:
    """A nav_msgs/Odometry JSON published on robot/odom is what the agent reports next,
    with a fresh timestamp; garbage on the topic is counted and ignored."""
    source = OdometryPose(f"mqtt://127.0.0.1:{mosquitto}", "robot/odom")
    ros = make_client("fake-ros")
    ros.connect("127.0.0.1", mosquitto)
    ros.loop_start()
    try:
        time.sleep(0.5)  # let the subscription settle
        ros.publish("robot/odom", b"garbage", qos=1)
        odom = {
            "pose": {
                "pose": {
                    "position": {"x": 4.25, "y": 3.5, "z": 0.0},
                    "orientation": {"x": 0, "y": 0, "z": 0.3827, "w": 0.9239},
                }
            },
            "status": {"battery": {"battery_level": 61.0, "charging": False}, "loaded": True},
        }
        ros.publish("robot/odom", msgspec.json.encode(odom), qos=1)
        deadline = time.monotonic() + 10
        while source.read() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert source.read() is not None and source.bad == 1
        agent = RobotAgent(
            MAPS / "depot.yaml", "ros-1", "http://unused", "mqtt://unused", pose_source=source
        )
        agent.client = CapturingClient()
        before = time.time_ns() // 1_000_000
        assert agent.publish_pose()
        topic, payload = agent.client.published[0]
        doc = msgspec.json.decode(payload)
        assert topic == "iot/coordinates/ros-1" and doc["robotId"] == "ros-1"
        assert doc["pose"]["position"] == {"x": 4.25, "y": 3.5, "z": 0}
        assert doc["pose"]["orientation"]["z"] == 0.3827
        assert doc["status"] == {
            "battery": {"battery_level": 61.0, "charging": False},
            "loaded": True,
        }
        assert parse_timestamp(doc["timestamp"]) >= before - 1000
    finally:
        ros.loop_stop()
        ros.disconnect()
        source.close()
