"""An operator pauses one of npm vda-5050-lib's virtual vehicles (2.0.0) through the API:
the gateway sends it `startPause` as instantActions, the vehicle (code nobody here wrote)
pauses, and its actionStates come back as the command's ack and outcome. Skipped without
npm, like test_vda5050_lib.py."""

from __future__ import annotations

import time

import httpx
import pytest

from tests.fixtures.vda5050_fleet import FleetProcess, Recorder, installed_fleet

from .conftest import start_stack

OPERATOR = "operator-" + "p" * 32


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    installed_fleet()  # skips before a stack starts if npm is absent
    stack = start_stack(tmp_path_factory, "mosquitto", {"MAPSERVICE_API_OPERATOR_TOKENS": OPERATOR})
    yield stack
    stack.stop()


def send(stack, body: dict) -> httpx.Response:
    return httpx.post(
        f"{stack.api_url}/api/v1/commands",
        json=body,
        timeout=30,
        headers={"Authorization": f"Bearer {OPERATOR}"},
    )


def test_a_pause_reaches_a_vda_5050_lib_vehicle_and_its_action_state_answers(stack, tmp_path):
    port = int(stack.mqtt_url.rsplit(":", 1)[1])
    recorder = Recorder(port)
    vehicle = FleetProcess(
        "vehicle",
        {
            "broker": stack.mqtt_url,
            "interface": "uagv",
            "vdaVersion": "2.0.0",
            "manufacturer": "Acme",
            "serialNumber": "P1",
            "batteryCharge": 70.0,
            "initialPosition": {"mapId": "hall", "x": 1.0, "y": 1.0, "theta": 0.0},
            "speed": 1.0,
            "timeLapse": 1,
            "visualizationMs": 200,
        },
        tmp_path,
        "vehicle-pause",
    )
    started_ms = time.time_ns() // 1_000_000
    try:
        vehicle.wait_for("started", 30)
        deadline = time.monotonic() + 60
        while (
            r := send(stack, {"robotId": "Acme:P1", "kind": "pause", "id": "vda-pause-1"})
        ).status_code == 404 and time.monotonic() < deadline:
            time.sleep(0.5)  # until its first pose is stored
        assert r.status_code == 202, r.text
        command: dict = {}
        while time.monotonic() < deadline:
            rows = httpx.get(
                f"{stack.api_url}/api/v1/commands",
                timeout=30,
                params={
                    "from": started_ms,
                    "to": time.time_ns() // 1_000_000 + 60_000,
                    "robot": "Acme:P1",
                },
            ).json()["commands"]
            command = next((c for c in rows if c["commandId"] == "vda-pause-1"), {})
            if command.get("outcome"):
                break
            time.sleep(0.25)
        sent = [m for _, topic, m in recorder.messages if topic.endswith("/instantActions")]
        states = [m for _, m in recorder.of("state", "Acme", "P1")]
        paused = [m["paused"] for m in states]
    finally:
        vehicle.stop()
        recorder.stop()
    assert sent and sent[0]["instantActions"][0]["actionType"] == "startPause", sent
    assert paused and paused[-1] is True, (paused, command, states[-1], sent)
    assert command["ack"]["status"] == "accepted", command
    assert command["outcome"]["status"] == "done", command
