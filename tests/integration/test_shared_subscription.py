"""Gateway replicas behind an MQTT shared subscription split the load and lose nothing."""

from __future__ import annotations

import re
import subprocess
import sys

import httpx

from mapservice.local.embedded import free_port, wait_for_port
from mapservice.local.stack import Stack

from .conftest import start_stack, wait_for_count
from .test_pipeline import now_ms, pose_and_chunk_messages, publish_all


def accepted(health_port: int) -> float:
    text = httpx.get(f"http://127.0.0.1:{health_port}/metrics").text
    match = re.search(
        r'^mapservice_gateway_messages_total\{outcome="accepted"\} (\S+)$', text, re.M
    )
    return float(match.group(1)) if match else 0.0


def test_two_gateways_share_the_subscription(tmp_path_factory):
    """With $share, two gateway replicas each take part of the messages and all arrive once."""
    stack: Stack | None = None
    second = None
    try:
        stack = start_stack(
            tmp_path_factory,
            "mosquitto",
            extra_env={
                "MAPSERVICE_MQTT_SHARE_GROUP": "mapservice",
                "MAPSERVICE_MQTT_CLIENT_ID": "gw-1",
            },
        )
        second_port = free_port()
        env = {**stack.env(), "MAPSERVICE_MQTT_CLIENT_ID": "gw-2"}
        second = subprocess.Popen(
            [sys.executable, "-m", "mapservice.cli", "gateway", "--health-port", str(second_port)],
            env=env,
            stdout=open(stack.log_dir / "gateway-2.log", "ab"),
            stderr=subprocess.STDOUT,
        )
        wait_for_port(second_port, proc=second, what="second gateway")
        stack.wait_healthy(f"http://127.0.0.1:{second_port}/healthz", "gateway-2", second)

        start = now_ms() - 60_000
        poses, chunks = pose_and_chunk_messages("shared", robots=10, per_robot=40, start_ms=start)
        publish_all(stack, poses + chunks)
        stored = wait_for_count(stack, "pose", "shared", start, start + 120_000, len(poses))
        assert len(stored) == len(set(stored)) == len(poses)
        first_share, second_share = accepted(stack.health_port), accepted(second_port)
        assert first_share > 0 and second_share > 0
        assert first_share + second_share >= len(poses) + len(chunks)
    finally:
        if second is not None:
            second.terminate()
            second.wait(10)
        if stack is not None:
            stack.stop()
