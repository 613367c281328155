"""Operators' commands end to end on a real Mosquitto with robot identities (password file
and ACL), the embedded Kafka and ClickHouse, the gateway and the processors + API:

- a pause sent through the API reaches a simulated robot over MQTT (its own topic, QoS 1),
  its stored poses stop changing within 2 s while it keeps reporting, the command and the
  robot's ack are stored with who sent it; a resume lets it drive again;
- a reader token cannot send a command (403, saying why);
- robot B cannot read robot A's commands (not on A's topic, not by a wildcard) and cannot
  publish on A's answer topic; an answer to A's command from B's own topic is a dead
  letter (not_its_command), A's own answer is stored.
"""

from __future__ import annotations

import json
import threading
import time

import httpx
import paho.mqtt.client as mqtt
import pytest

from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.core.events import decode_dead_letter
from mapservice.core.wire2019 import format_timestamp
from mapservice.local.stack import Stack
from mapservice.robot.connection import RobotMqtt, load_credentials
from mapservice.robot.sim import SimConfig, sim_robot_id
from mapservice.robot.simrun import SimRunner
from tests.fixtures.paths import MAPS

from .conftest import read_topic, run_stack, wait_for_count
from .test_robot_identity import Robot, now_ms, pose

OPERATOR = "operator-" + "p" * 32
READER = "viewer-" + "r" * 32
SIM_PREFIX = "cmd"
PAUSED = sim_robot_id(SIM_PREFIX, 0)
OTHER = sim_robot_id(SIM_PREFIX, 1)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = Stack(
        tmp_path_factory.mktemp("stack-commands"),
        mqtt="mosquitto",
        mqtt_auth=True,
        extra_env={
            "MAPSERVICE_API_OPERATOR_TOKENS": OPERATOR,
            "MAPSERVICE_API_READER_TOKENS": READER,
        },
    )
    yield run_stack(stack, meta_for(load_ros_map(MAPS / "depot.yaml")))
    stack.stop()


@pytest.fixture(scope="module")
def robots(stack):
    """Every identity the module uses, made before any robot connects (each one makes the
    broker read its files again, which drops connected clients)."""
    credentials = load_credentials(stack.robot_credentials([PAUSED, OTHER]))
    return {"a": stack.add_robot("acl-a"), "b": stack.add_robot("acl-b"), "sim": credentials}


@pytest.fixture(scope="module")
def simulator(stack, robots):
    runner = SimRunner(
        stack.mqtt_url,
        load_ros_map(MAPS / "depot.yaml"),
        2,
        prefix=SIM_PREFIX,
        config=SimConfig(change_every_s=0, dwell_s=0.5),
        mqtt_conn=RobotMqtt(stack.mqtt_url, robots["sim"]),
    )
    thread = threading.Thread(target=runner.run, kwargs={"seconds": 240}, daemon=True)
    thread.start()
    yield runner
    runner.stop()
    thread.join(10)


def send(stack: Stack, body: dict, token: str = OPERATOR) -> httpx.Response:
    return httpx.post(
        f"{stack.api_url}/api/v1/commands",
        json=body,
        timeout=30,
        headers={"Authorization": f"Bearer {token}"},
    )


def positions(stack: Stack, robot: str, from_ms: int, to_ms: int) -> list[tuple[int, float, float]]:
    rows = httpx.get(
        f"{stack.api_url}/api/v1/poses",
        params={"robotId": robot, "from": from_ms, "to": to_ms, "limit": 10_000},
        timeout=30,
    ).json()
    return sorted(
        (r["ts_ms"], r["position"][0], r["position"][1]) for r in rows if r["robotId"] == robot
    )


def stored_command(
    stack: Stack,
    robot: str,
    command_id: str,
    since_ms: int,
    timeout_s: float = 30,
    until=lambda c: c["ack"] is not None,
) -> dict:
    deadline = time.monotonic() + timeout_s
    found: dict = {}
    while time.monotonic() < deadline:
        rows = httpx.get(
            f"{stack.api_url}/api/v1/commands",
            params={"from": since_ms, "to": now_ms() + 60_000, "robot": robot},
            timeout=30,
        ).json()["commands"]
        found = next((c for c in rows if c["commandId"] == command_id), {})
        if found and until(found):
            return found
        time.sleep(0.25)
    raise AssertionError(
        f"command {command_id} not stored with its answer in {timeout_s} s: {found}"
    )


def test_a_pause_stops_a_simulated_robots_poses_within_2_s(stack, simulator):
    start = now_ms()
    assert len(wait_for_count(stack, "pose", PAUSED, start - 5_000, start + 120_000, 3)) >= 3
    # Wait until the robot is driving (two latest stored poses apart), then pause it.
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        recent = positions(stack, PAUSED, now_ms() - 4_000, now_ms() + 1_000)
        if len(recent) >= 2 and recent[-1][1:] != recent[-2][1:]:
            break
        time.sleep(0.5)
    else:
        raise AssertionError("the simulated robot never drove")
    refused = send(stack, {"robotId": PAUSED, "kind": "pause"}, READER)
    assert refused.status_code == 403 and "may not" in refused.json()["detail"]
    r = send(stack, {"robotId": PAUSED, "kind": "pause", "id": "pause-1"})
    assert r.status_code == 202, r.text
    issued = r.json()["issued_ms"]
    time.sleep(8)
    after = positions(stack, PAUSED, issued + 2_000, now_ms() + 1_000)
    assert len(after) >= 4, after  # still reporting, once a second
    assert len({(x, y) for _, x, y in after}) == 1, f"moved after the pause: {after}"
    other = positions(stack, OTHER, issued + 2_000, now_ms() + 1_000)
    assert len({(x, y) for _, x, y in other}) > 1  # the other robot drives on
    command = stored_command(
        stack, PAUSED, "pause-1", issued - 1_000, until=lambda c: c["outcome"] is not None
    )
    assert command["issuedBy"].startswith("operator") and OPERATOR not in command["issuedBy"]
    assert command["kind"] == "pause" and command["issued_ms"] == issued
    assert command["ack"]["status"] == "accepted" and command["ack"]["ts_ms"] - issued < 2_000
    assert command["outcome"]["status"] == "done"
    held = after[-1][1:]
    r = send(stack, {"robotId": PAUSED, "kind": "resume"})
    assert r.status_code == 202, r.text
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if any(
            (x, y) != held
            for _, x, y in positions(stack, PAUSED, r.json()["issued_ms"], now_ms() + 1_000)
        ):
            break
        time.sleep(0.5)
    else:
        raise AssertionError("the robot did not drive again after resume")


def test_robot_b_cannot_read_or_answer_robot_as_commands(stack, robots):
    a, b = robots["a"], robots["b"]
    ts = now_ms() - 1_000
    robot_a = Robot(stack.mqtt_url, a.username, a.password)
    robot_b = Robot(stack.mqtt_url, b.username, b.password, protocol=mqtt.MQTTv5)
    try:
        robot_a.publish(a.topics["pose"], pose(a.robot_id, ts))  # known to the API from now on
        wait_for_count(stack, "pose", a.robot_id, ts - 1, ts + 1, 1)
        robot_a.client.subscribe(a.topics["commands"], 1)
        assert robot_a.subscribed.wait(5)
        for spy in (a.topics["commands"], "iot/robots/+/commands", "iot/robots/#"):
            robot_b.subscribed.clear()
            robot_b.client.subscribe(spy, 1)
            assert robot_b.subscribed.wait(5)
        r = send(stack, {"robotId": a.robot_id, "kind": "pause", "id": "acl-1"})
        assert r.status_code == 202, r.text
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not robot_a.received:
            time.sleep(0.1)
        ((topic, payload),) = robot_a.received
        assert topic == a.topics["commands"] == f"iot/robots/{a.robot_id}/commands"
        assert json.loads(payload)["commandId"] == "acl-1"
        time.sleep(2)  # anything B could read would have arrived by now
        assert robot_b.received == []
        answer = {
            "robotId": a.robot_id,
            "commandId": "acl-1",
            "type": "ack",
            "status": "rejected",
            "reason": "forged by b",
            "timestamp": format_timestamp(now_ms()),
        }
        forged = robot_b.publish(a.topics["commandEvents"], json.dumps(answer).encode())
        deadline = time.monotonic() + 5
        while forged.mid not in robot_b.puback and time.monotonic() < deadline:
            time.sleep(0.05)
        assert robot_b.puback[forged.mid] == "Not authorized"
        own_topic = {**answer, "robotId": b.robot_id}
        robot_b.publish(b.topics["commandEvents"], json.dumps(own_topic).encode())
        honest = {**answer, "status": "accepted", "reason": ""}
        robot_a.publish(a.topics["commandEvents"], json.dumps(honest).encode())
    finally:
        robot_a.close()
        robot_b.close()
    command = stored_command(stack, a.robot_id, "acl-1", ts - 1_000)
    assert command["ack"]["status"] == "accepted" and command["ack"]["reason"] == ""
    letters = [
        decode_dead_letter(v) for v in read_topic(stack, stack.settings().topic_dead_letter, 1)
    ]
    mine = [d for d in letters if d.mqtt_topic == b.topics["commandEvents"]]
    assert [d.reason for d in mine] == ["not_its_command"], letters
