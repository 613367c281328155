"""No message stops ingest: a 2 KB message nested 1,000 deep and a 1.2 MB message,
then a good one, through Mosquitto, the gateway, Apache Kafka and the processors. The good one is
stored within seconds, the bad ones are dead letters with their reasons, the gateway's
health stays truthful; and with Mosquitto's persistent session the same holds when the
messages wait for a gateway that was down. Bounded: about half a minute."""

from __future__ import annotations

import os
import signal
import time

import httpx
import pytest

from mapservice.core.events import decode_dead_letter
from mapservice.core.wire2019 import encode_coordinates, format_timestamp

from .conftest import read_topic, wait_for_count
from .test_pipeline import now_ms, publish_all

DEEP = b'{"x":' + b"[" * 1000 + b"]" * 1000 + b"}"
HUGE = b'{"robotId": "poison-huge", "x": "' + b"a" * 1_200_000 + b'"}'


def health(stack) -> dict:
    return httpx.get(f"http://127.0.0.1:{stack.health_port}/healthz", timeout=5).json()


def letters_for(stack, robot_topic: str, count: int) -> list:
    values = read_topic(stack, stack.settings().topic_dead_letter, min_records=count, timeout_s=30)
    return [d for d in map(decode_dead_letter, values) if d.mqtt_topic == robot_topic]


def good_pose(robot: str, ts_ms: int) -> tuple[str, bytes]:
    return f"iot/coordinates/{robot}", encode_coordinates(
        robot, format_timestamp(ts_ms), 1.0, 2.0, battery_level=50.0
    )


def test_poison_messages_are_dead_letters_and_the_next_message_is_stored(mosquitto_stack):
    """Deep nesting and 1.2 MB become dead letters (too_deep, oversized); a good pose after them is stored in seconds."""
    stack = mosquitto_stack
    t = now_ms() - 5_000
    topic = "iot/coordinates/poison-a"
    publish_all(stack, [(topic, DEEP), (topic, HUGE), good_pose("poison-a", t)])
    stored = wait_for_count(stack, "pose", "poison-a", t - 1, t + 1, 1, timeout_s=15)
    assert len(stored) == 1
    reasons = {d.reason: d for d in letters_for(stack, topic, 2)}
    assert {"too_deep", "oversized"} <= set(reasons)
    assert reasons["too_deep"].payload == DEEP
    assert (
        len(reasons["oversized"].payload) == 64 * 1024
        and str(len(HUGE)) in reasons["oversized"].detail
    )
    status = health(stack)
    assert status["ok"] and status["mqtt_connected"] and status["mqtt_loop_alive"]
    assert status["in_flight"] == 0


def test_poison_waiting_in_a_persistent_session_does_not_stop_a_restarted_gateway(mosquitto_stack):
    """Published while the gateway is down, the poison waits in its Mosquitto session; the restarted gateway dead-letters it and stores the good pose."""
    stack = mosquitto_stack
    gateway = stack.procs["gateway"]
    os.kill(gateway.pid, signal.SIGKILL)
    gateway.wait()
    t = now_ms() - 5_000
    topic = "iot/coordinates/poison-b"
    publish_all(stack, [(topic, DEEP), (topic, HUGE), good_pose("poison-b", t)])
    stack.start_gateway()
    stored = wait_for_count(stack, "pose", "poison-b", t - 1, t + 1, 1, timeout_s=20)
    assert len(stored) == 1
    assert {"too_deep", "oversized"} <= {d.reason for d in letters_for(stack, topic, 2)}
    deadline = time.monotonic() + 10
    while health(stack)["in_flight"] and time.monotonic() < deadline:
        time.sleep(0.2)
    status = health(stack)
    assert status["ok"] and status["mqtt_loop_alive"] and status["in_flight"] == 0


@pytest.fixture(autouse=True)
def _bounded():
    started = time.monotonic()
    yield
    assert time.monotonic() - started < 120
