"""Gateway replicas behind an MQTT shared subscription split the load and lose nothing."""

from __future__ import annotations

import re
import time

import httpx
import paho.mqtt.client as mqtt

from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.local.stack import Stack
from tests.fixtures.paths import MAPS

from .conftest import run_stack, start_stack, wait_for_count
from .test_pipeline import now_ms, pose_and_chunk_messages, publish_all
from .test_robot_identity import Robot, pose


def accepted(health_port: int) -> float:
    text = httpx.get(f"http://127.0.0.1:{health_port}/metrics").text
    match = re.search(
        r'^mapservice_gateway_messages_total\{outcome="accepted"\} (\S+)$', text, re.M
    )
    return float(match.group(1)) if match else 0.0


def test_two_gateways_share_the_subscription(tmp_path_factory):
    """With $share, two gateway replicas each take part of the messages and all arrive once."""
    stack: Stack | None = None
    try:
        stack = start_stack(tmp_path_factory, "mosquitto", gateways=2)
        second_port = stack.gateway_health_ports[1]

        start = now_ms() - 60_000
        poses, chunks = pose_and_chunk_messages("shared", robots=10, per_robot=40, start_ms=start)
        publish_all(stack, poses + chunks)
        stored = wait_for_count(stack, "pose", "shared", start, start + 120_000, len(poses))
        assert len(stored) == len(set(stored)) == len(poses)
        first_share, second_share = accepted(stack.health_port), accepted(second_port)
        assert first_share > 0 and second_share > 0
        assert first_share + second_share >= len(poses) + len(chunks)
    finally:
        if stack is not None:
            stack.stop()


def test_a_robot_cannot_join_the_gateways_group(tmp_path_factory):
    """With robot identities and the share group on, a robot's subscription to the
    gateways' `$share/<group>/...` is refused in its SUBACK and all 100 poses it then
    sends are stored (a member the broker denies each message would have dropped its turn)."""
    share = "mapservice"
    stack = Stack(
        tmp_path_factory.mktemp("stack-shared-auth"),
        mqtt="mosquitto",
        mqtt_auth=True,
        extra_env={"MAPSERVICE_MQTT_SHARE_GROUP": share},
    )
    robot = None
    try:
        # Before the broker starts: a restart for a new user could come between the gateway's
        # connection and its subscription, and poses sent then would find no subscriber.
        credential = stack.broker_files.add_robot("share-intruder")
        run_stack(stack, meta_for(load_ros_map(MAPS / "depot.yaml")))
        robot = Robot(
            stack.mqtt_url, credential.username, credential.password, protocol=mqtt.MQTTv5
        )
        codes: list = []
        robot.client.on_subscribe = lambda _c, _u, _m, reason_codes, _p: codes.extend(reason_codes)
        settings = stack.settings()
        robot.client.subscribe([(topic, 1) for topic in settings.mqtt_subscriptions])
        deadline = time.monotonic() + 10
        while len(codes) < len(settings.mqtt_subscriptions) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(codes) == len(settings.mqtt_subscriptions)

        start = now_ms() - 60_000
        for k in range(100):
            info = robot.publish(
                credential.topics["pose"], pose(credential.robot_id, start + k * 100, x=1.0 + k % 7)
            )
            assert info.is_published()
        stored = wait_for_count(
            stack, "pose", credential.robot_id, start, start + 60_000, 100, timeout_s=30
        )
        assert len(stored) == len(set(stored)) == 100, f"stored {len(stored)} of 100"
        assert all(code.is_failure for code in codes), [str(c) for c in codes]
    finally:
        if robot is not None:
            robot.close()
        stack.stop()
