"""Where the robot agent's pose comes from: a simulated drive on the robot's own map, or JSON
odometry on a local MQTT topic (the 2019 ROS bridge)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace

import msgspec
import paho.mqtt.client as mqtt

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.adapters.ros_map import RosMap

from .commands import SimCommands
from .faults import yaw_quaternion


@dataclass(frozen=True)
class PoseReading:
    x: float
    y: float
    yaw_q: tuple[float, float, float, float]
    battery: float = 100.0
    charging: bool = False
    loaded: bool = False
    path: tuple[tuple[float, float], ...] | None = None


class SimulatedPose:
    """One robot of the simulator, driving between stations of the robot's own map."""

    def __init__(self, ros_map: RosMap, robot_id: str, seed: int = 0) -> None:
        from .sim import SimConfig, new_state

        seed = seed or sum(robot_id.encode())
        state = new_state(ros_map, 1, seed=seed, config=SimConfig(change_every_s=0))
        self.state = replace(state, robots=(replace(state.robots[0], robot_id=robot_id),))
        self.commands: SimCommands | None = None  # the agent's, once it reads commands

    def read(self) -> PoseReading | None:
        from .sim import step

        if self.commands is None:
            self.state, out = step(self.state)
        else:
            before = self.commands.before_step(self.state)
            self.state, out = self.commands.after_step(before, *step(before))
        p = out.poses[0]
        return PoseReading(p.x, p.y, yaw_quaternion(p.yaw), p.battery, p.charging, p.loaded, p.path)


def parse_odometry(data: bytes) -> PoseReading | None:
    """nav_msgs/Odometry as JSON ({"pose": {"pose": {...}}}), a bare geometry_msgs/Pose
    ({"position", "orientation"}) or one wrapped in "pose"; optional battery/charging/loaded."""
    try:
        doc = msgspec.json.decode(data)
        pose = doc
        while isinstance(pose, dict) and "pose" in pose and "position" not in pose:
            pose = pose["pose"]
        pos, ori = pose["position"], pose.get("orientation") or {"x": 0, "y": 0, "z": 0, "w": 1}
        status = doc.get("status") or {}
        battery = (status.get("battery") or {}) if isinstance(status, dict) else {}
        return PoseReading(
            float(pos["x"]),
            float(pos["y"]),
            (float(ori["x"]), float(ori["y"]), float(ori["z"]), float(ori["w"])),
            float(battery.get("battery_level", doc.get("battery", 100.0))),
            bool(battery.get("charging", doc.get("charging", False))),
            bool(status.get("loaded", doc.get("loaded", False))),
        )
    except (msgspec.DecodeError, KeyError, TypeError, ValueError, AttributeError):
        return None


class OdometryPose:
    """The latest odometry message of a local MQTT topic, re-stamped when published."""

    def __init__(self, mqtt_url: str, topic: str) -> None:
        self.latest: PoseReading | None = None
        self.bad = 0
        host, port, tls = parse_mqtt_url(mqtt_url)
        self.client = make_client(f"odom-{os.getpid()}-{time.time_ns() % 10**6}", tls=tls)
        self.client.on_connect = lambda c, *_: c.subscribe(topic, qos=0)
        self.client.on_message = self._on_message
        self.client.connect(host, port, keepalive=30)
        self.client.loop_start()

    def _on_message(self, client: mqtt.Client, userdata: object, msg: mqtt.MQTTMessage) -> None:
        reading = parse_odometry(msg.payload)
        if reading is None:
            self.bad += 1
        else:
            self.latest = reading

    def read(self) -> PoseReading | None:
        return self.latest

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()
