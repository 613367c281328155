"""VDA 5050 vehicles against the embedded Mosquitto and the real pipeline (gateway, Kafka,
processors, chDB, API). The vehicles are Python publishers of schema-valid VDA 5050 2.0.0
and 2.1.0 messages (tests/fixtures/vda5050.py), not npm vda-5050-lib's virtual AGV: they
report states and visualizations along a route, one charges and raises an error, and one
drops its connection so the broker sends its CONNECTIONBROKEN last will."""

from __future__ import annotations

import math
import time

import httpx
import pytest

from mapservice.adapters.mqtt_client import make_client
from tests.fixtures import vda5050 as vda

from .conftest import start_stack


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = start_stack(tmp_path_factory, "mosquitto")
    yield stack
    stack.stop()


def now_ms() -> int:
    return time.time_ns() // 1_000_000


class Vehicle:
    """One VDA 5050 vehicle's MQTT session, with its last will as the standard asks."""

    def __init__(self, port: int, version: str, manufacturer: str, serial: str) -> None:
        self.version, self.m, self.s = version, manufacturer, serial
        self.base = f"uagv/v2/{manufacturer}/{serial}"
        self.client = make_client(f"vda-{manufacturer}-{serial}")
        will = vda.connection(version, manufacturer, serial, now_ms(), "CONNECTIONBROKEN")
        self.client.will_set(f"{self.base}/connection", vda.encode(will), qos=1, retain=True)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def publish(self, subtopic: str, msg: dict, retain: bool = False) -> None:
        self.client.publish(
            f"{self.base}/{subtopic}", vda.encode(msg), qos=1, retain=retain
        ).wait_for_publish(10)


def test_vehicles_drive_charge_fail_and_drop_their_connection(stack) -> None:
    start = now_ms()
    port = int(stack.mqtt_url.rsplit(":", 1)[1])
    a = Vehicle(port, "2.0.0", "Acme", "001")
    b = Vehicle(port, "2.1.0", "Robo Co", "7:2")
    reported: dict[str, list[tuple[int, float, float, float]]] = {
        "Acme:001": [],
        "Robo@20Co:7@3A2": [],
    }
    for v in (a, b):
        v.publish(
            "connection", vda.connection(v.version, v.m, v.s, now_ms(), "ONLINE"), retain=True
        )
        v.publish("factsheet", vda.factsheet(v.version, v.m, v.s, now_ms()), retain=True)
    for step in range(6):  # drive along x; a state every third message, visualizations between
        for v, robot, charging in ((a, "Acme:001", False), (b, "Robo@20Co:7@3A2", True)):
            t = now_ms()
            x, y, theta = 1.0 + step, 2.0 + 0.5 * step, 0.1 * step
            if step % 3 == 0:
                errors = (("WARNING", "lowBattery", "charge me"),) if charging else ()
                v.publish(
                    "state",
                    vda.state(
                        v.version,
                        v.m,
                        v.s,
                        t,
                        x=x,
                        y=y,
                        theta=theta,
                        battery=50.0 + step,
                        charging=charging,
                        loads=[{"loadId": "L1"}] if not charging else [],
                        nodes=((9.0, 9.0),),
                        errors=errors,
                    ),
                )
            else:
                v.publish(
                    "visualization",
                    vda.visualization(v.version, v.m, v.s, t, x=x, y=y, theta=theta),
                )
            reported[robot].append((t, x, y, theta))
        time.sleep(0.05)
    # Vehicle b's connection breaks: its socket closes without a DISCONNECT.
    before_break = now_ms()
    b.client.loop_stop()
    b.client.socket().close()
    a.client.disconnect()
    a.client.loop_stop()

    deadline = time.monotonic() + 60
    poses: list = []
    facts: dict = {}
    while time.monotonic() < deadline:
        poses = httpx.get(
            f"{stack.api_url}/api/v1/poses",
            params={"from": start, "to": now_ms() + 1000, "limit": 1000},
            timeout=30,
        ).json()
        facts = httpx.get(
            f"{stack.api_url}/api/v1/robots/Robo@20Co:7@3A2/vda5050", timeout=30
        ).json()
        if len(poses) >= 12 and len(facts.get("connections", ())) >= 2:
            break
        time.sleep(0.5)
    by_robot: dict[str, list] = {}
    for p in poses:
        by_robot.setdefault(p["robotId"], []).append(p)
    for robot, sent in reported.items():
        got = sorted(by_robot[robot], key=lambda p: p["ts_ms"])
        assert [p["ts_ms"] for p in got] == [t for t, *_ in sent]
        for p, (_, x, y, theta) in zip(got, sent):
            assert p["position"][:2] == pytest.approx([x, y], abs=0.001)  # stored in mm
            assert p["orientation"][2:] == pytest.approx(
                [math.sin(theta / 2), math.cos(theta / 2)], abs=1e-6
            )
            assert p["battery_level"] is not None  # visualizations carry the state's battery
    assert [p["battery_level"] for p in sorted(by_robot["Acme:001"], key=lambda p: p["ts_ms"])] == [
        50.0,
        50.0,
        50.0,
        53.0,
        53.0,
        53.0,
    ]
    assert {(p["charging"], p["loaded"]) for p in by_robot["Robo@20Co:7@3A2"]} == {(True, False)}
    assert {(p["charging"], p["loaded"]) for p in by_robot["Acme:001"]} == {(False, True)}
    assert by_robot["Acme:001"][0]["path"] == [[9.0, 9.0]]

    assert (facts["manufacturer"], facts["serialNumber"], facts["online"]) == (
        "Robo Co",
        "7:2",
        False,
    )
    states = [(c["state"], c["ts_ms"]) for c in facts["connections"]]
    assert states[0][0] == "ONLINE" and states[-1][0] == "CONNECTIONBROKEN"
    assert before_break <= states[-1][1] <= now_ms()  # offline at the break, not at connect
    assert {(e["level"], e["type"]) for e in facts["errors"]} == {("WARNING", "lowBattery")}
    assert facts["factsheet"]["vda_version"] == "2.1.0"
    assert facts["factsheet"]["factsheet"]["serialNumber"] == "7:2"
