"""The acceptance test of VDA 5050 ingest with a fleet nobody here wrote: npm vda-5050-lib's
virtual vehicles (AgvController + VirtualAgvAdapter, VDA 5050 2.0.0) and its
MasterController, against the embedded Mosquitto and the real pipeline (gateway, Kafka,
processors, chDB, API), with a map transform for the vehicles' map id.

Three vehicles: Acme/001 picks a load, drives it two edges and drops it; "Robo Co"/7:2
drives to a charger and charges; Acme/003 gets an order it cannot reach (it raises a
noRouteError), then drives one, and its process is killed (the broker publishes its
CONNECTIONBROKEN last will). Every position the vehicles published (recorded off the
broker) must be in the history at its instant, transformed into the map's frame, with
the battery, charging, loaded and path of the vehicle's latest state, the error among its
facts and its offline instant at the break.
"""

from __future__ import annotations

import csv
import io
import json
import math
import signal
import time

import httpx
import pytest

from mapservice.adapters.mqtt_client import make_client
from mapservice.core.vda_ids import robot_id_for
from tests.fixtures.vda5050_fleet import FleetProcess, Recorder, installed_fleet, vda_ms

from .conftest import start_stack

MAP_ID = "hall"
TRANSFORM = (3.0, 2.0, 0.3)  # dx, dy (m), rotation (rad): hall's frame -> the depot map's
BUDGET_S = 120


def transformed(x: float, y: float) -> tuple[float, float]:
    dx, dy, r = TRANSFORM
    return math.cos(r) * x - math.sin(r) * y + dx, math.sin(r) * x + math.cos(r) * y + dy


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    installed_fleet()  # skips before a stack starts if npm is absent
    stack = start_stack(
        tmp_path_factory,
        "mosquitto",
        {"MAPSERVICE_VDA5050_MAP_TRANSFORMS": json.dumps({MAP_ID: list(TRANSFORM)})},
    )
    yield stack
    stack.stop()


def node(node_id: str, seq: int, x: float, y: float, *actions: dict) -> dict:
    return {
        "nodeId": node_id,
        "sequenceId": seq,
        "released": True,
        "nodePosition": {"x": x, "y": y, "mapId": MAP_ID},
        "actions": list(actions),
    }


def edge(seq: int, start: str, end: str) -> dict:
    return {
        "edgeId": f"{start}-{end}",
        "sequenceId": seq,
        "startNodeId": start,
        "endNodeId": end,
        "released": True,
        "actions": [],
    }


def action(action_id: str, action_type: str, **params) -> dict:
    return {
        "actionId": action_id,
        "actionType": action_type,
        "blockingType": "HARD",
        "actionParameters": [{"key": k, "value": v} for k, v in params.items()],
    }


def route(order_id: str, *points: tuple[str, float, float, list]) -> dict:
    nodes = [node(n, 2 * i, x, y, *acts) for i, (n, x, y, acts) in enumerate(points)]
    edges = [
        edge(2 * i + 1, a["nodeId"], b["nodeId"]) for i, (a, b) in enumerate(zip(nodes, nodes[1:]))
    ]
    return {"orderId": order_id, "orderUpdateId": 0, "nodes": nodes, "edges": edges}


EPAL = {"stationType": "floor", "loadType": "EPAL", "duration": 0.5}
VEHICLES = {  # (manufacturer, serial): (start x, y, theta, battery, orders)
    ("Acme", "001"): (
        1.0,
        1.0,
        0.0,
        80.0,
        [
            route(
                "acme-1",
                ("a0", 1.0, 1.0, [action("pick-1", "pick", **EPAL)]),
                ("a1", 5.0, 1.0, []),
                ("a2", 5.0, 3.0, [action("drop-1", "drop", **EPAL)]),
            )
        ],
    ),
    ("Robo Co", "7:2"): (
        2.0,
        4.0,
        0.0,
        30.0,
        [
            route(
                "robo-1",
                ("r0", 2.0, 4.0, []),
                ("r1", 4.0, 5.0, [action("charge-1", "startCharging", duration=0.2)]),
            )
        ],
    ),
    ("Acme", "003"): (
        1.0,
        6.0,
        0.0,
        60.0,
        [
            route("acme3-far", ("far", 20.0, 9.0, [])),  # not where it stands: noRouteError
            route("acme3-1", ("c0", 1.0, 6.0, []), ("c1", 4.0, 6.5, [])),
        ],
    ),
}


def test_vda_5050_lib_fleet_in_the_history(stack, tmp_path) -> None:
    port = int(stack.mqtt_url.rsplit(":", 1)[1])
    common = {"broker": stack.mqtt_url, "interface": "uagv", "vdaVersion": "2.0.0"}
    recorder = Recorder(port)
    started_ms = time.time_ns() // 1_000_000
    vehicles: dict[tuple[str, str], FleetProcess] = {}
    master = None
    try:
        for (m, s), (x, y, theta, battery, _) in VEHICLES.items():
            vehicles[m, s] = FleetProcess(
                "vehicle",
                {
                    **common,
                    "manufacturer": m,
                    "serialNumber": s,
                    "batteryCharge": battery,
                    "initialPosition": {"mapId": MAP_ID, "x": x, "y": y, "theta": theta},
                    "speed": 2.0,
                    "timeLapse": 1,
                    "visualizationMs": 200,
                },
                tmp_path,
                f"vehicle-{m}-{s}".replace(" ", "_").replace(":", "_"),
            )
        for v in vehicles.values():
            v.wait_for("started", 30)
        master = FleetProcess(
            "master",
            {
                **common,
                "plans": [
                    {"agv": {"manufacturer": m, "serialNumber": s}, "orders": orders}
                    for (m, s), (*_, orders) in VEHICLES.items()
                ],
            },
            tmp_path,
            "master",
        )
        master.wait_for("done", BUDGET_S / 2)
        time.sleep(0.5)  # a few visualizations of them standing
        # Acme/003's process dies: its socket closes without a DISCONNECT.
        killed_ms = time.time_ns() // 1_000_000
        vehicles["Acme", "003"].stop(signal.SIGKILL)
        vehicles["Acme", "001"].stop()  # a graceful stop says OFFLINE
        deadline = time.monotonic() + 30
        while (
            not recorder.of("connection", "Acme", "003")[-1][1]["connectionState"]
            == "CONNECTIONBROKEN"
            and time.monotonic() < deadline
        ):
            time.sleep(0.05)
        will_received_ms = time.time_ns() // 1_000_000
    finally:
        for v in vehicles.values():
            v.stop()
        if master is not None:
            master.stop()
        recorder.stop()

    outcomes = {
        (e["agv"]["serialNumber"], e["orderId"]): e["withError"]
        for e in master.events
        if e["event"] == "processed"
    }
    assert outcomes == {
        ("001", "acme-1"): None,
        ("7:2", "robo-1"): None,
        ("003", "acme3-far"): "noRouteError",
        ("003", "acme3-1"): None,
    }

    expected = expected_poses(recorder)
    total = sum(len(rows) for rows in expected.values())
    assert total > 30  # 5 Hz visualizations plus states, three vehicles
    rows = wait_for_poses(stack, started_ms, total)
    for robot, want in expected.items():
        got = {p["ts_ms"]: p for p in rows if p["robotId"] == robot}
        assert sorted(got) == sorted(want), robot
        for ts, candidates in want.items():
            p = got[ts]
            assert any(matches(p, c) for c in candidates), json.dumps(
                {"robot": robot, "stored": p, "sent": candidates}
            )

    acme1 = [expected["Acme:001"][ts][-1] for ts in sorted(expected["Acme:001"])]
    assert [c["loaded"] for c in acme1].count(True) > 0  # carried between pick and drop
    assert not acme1[-1]["loaded"] and acme1[-1]["path"] is None  # dropped, order done
    assert any(c["path"] and len(c["path"]) == 2 for c in acme1)  # two nodes still to drive
    robo_poses = expected[robot_id_for("Robo Co", "7:2")].values()
    assert any(c["charging"] for candidates in robo_poses for c in candidates)

    facts = httpx.get(f"{stack.api_url}/api/v1/robots/Acme:003/vda5050", timeout=30).json()
    assert ("WARNING", "noRouteError") in {(e["level"], e["type"]) for e in facts["errors"]}
    states = [(c["state"], c["ts_ms"]) for c in facts["connections"]]
    assert states[0][0] == "ONLINE" and states[-1][0] == "CONNECTIONBROKEN"
    assert killed_ms <= states[-1][1] <= will_received_ms  # offline at the break
    assert facts["online"] is False
    acme1_facts = httpx.get(f"{stack.api_url}/api/v1/robots/Acme:001/vda5050", timeout=30).json()
    assert [c["state"] for c in acme1_facts["connections"]][-1] == "OFFLINE"
    robo = httpx.get(f"{stack.api_url}/api/v1/robots/Robo@20Co:7@3A2/vda5050", timeout=30).json()
    assert (robo["manufacturer"], robo["serialNumber"]) == ("Robo Co", "7:2")
    assert [c["state"] for c in robo["connections"]] == ["ONLINE", "OFFLINE"]  # stopped last

    # Nothing the fleet sent was refused: not the vehicles' messages, nor the master's
    # orders on the same subtree (not the gateway's to read). A probe that is refused,
    # sent last, shows the dead letters before it are stored.
    probe = make_client("vda-probe")
    probe.connect("127.0.0.1", port)
    probe.loop_start()
    probe.publish("uagv/v2/Probe/0/state", b'{"version": "9.9.9"}', qos=1).wait_for_publish(10)
    probe.disconnect()
    probe.loop_stop()
    letters = wait_for_dead_letter(stack, started_ms, "uagv/v2/Probe/0/state")
    assert [
        (r["mqtt_topic"], r["reason"]) for r in letters if r["mqtt_topic"].startswith("uagv/")
    ] == [("uagv/v2/Probe/0/state", "vda_unsupported_version")]


def wait_for_dead_letter(stack, started_ms: int, topic: str, timeout_s: float = 60) -> list[dict]:
    deadline = time.monotonic() + timeout_s
    rows: list[dict] = []
    while time.monotonic() < deadline:
        text = httpx.get(
            f"{stack.api_url}/api/v1/exports/tables/dead-letters",
            params={
                "from": started_ms - 1000,
                "to": time.time_ns() // 1_000_000 + 1000,
                "format": "csv",
            },
            timeout=30,
        ).text
        rows = list(csv.DictReader(io.StringIO(text)))
        if any(r["mqtt_topic"] == topic for r in rows):
            return rows
        time.sleep(0.5)
    raise AssertionError(f"the probe's dead letter never arrived; dead letters {rows}")


def expected_poses(recorder: Recorder) -> dict[str, dict[int, list[dict]]]:
    """Per robot, per instant, the poses the vehicle's messages there should be stored as
    (a state and a visualization may share a millisecond: either may be the one kept):
    the position transformed, the status of the vehicle's latest state before it."""
    out: dict[str, dict[int, list[dict]]] = {}
    for m, s in VEHICLES:
        status: dict = {"battery_level": None, "charging": None, "loaded": None, "path": None}
        robot = out.setdefault(robot_id_for(m, s), {})
        for _, topic, msg in recorder.messages:
            if not topic.startswith(f"uagv/v2/{m}/{s}/") or "agvPosition" not in msg:
                continue
            if topic.endswith("/state"):
                status = {
                    "battery_level": msg["batteryState"]["batteryCharge"],
                    "charging": msg["batteryState"]["charging"],
                    "loaded": bool(msg["loads"]) if "loads" in msg else None,
                    "path": [
                        list(transformed(n["nodePosition"]["x"], n["nodePosition"]["y"]))
                        for n in msg["nodeStates"]
                        if "nodePosition" in n
                    ]
                    or None,
                }
            elif not topic.endswith("/visualization"):
                continue
            pos = msg["agvPosition"]
            robot.setdefault(vda_ms(msg["timestamp"]), []).append(
                {
                    **status,
                    "xy": transformed(pos["x"], pos["y"]),
                    "theta": pos["theta"] + TRANSFORM[2],
                }
            )
    return out


def matches(stored: dict, want: dict) -> bool:
    theta = want["theta"]
    return (
        stored["position"][:2] == pytest.approx(list(want["xy"]), abs=0.0011)  # mm
        and stored["orientation"][2:]
        == pytest.approx([math.sin(theta / 2), math.cos(theta / 2)], abs=1e-6)
        # battery_level is stored as a Float32
        and (
            stored["battery_level"] == pytest.approx(want["battery_level"], rel=1e-6)
            if want["battery_level"] is not None
            else stored["battery_level"] is None
        )
        and (stored["charging"], stored["loaded"]) == (want["charging"], want["loaded"])
        and (
            flat(stored["path"]) == pytest.approx(flat(want["path"]), abs=0.0011)
            if want["path"]
            else not stored["path"]
        )
    )


def flat(path: list | None) -> list[float]:
    return [c for point in path or () for c in point]


def wait_for_poses(stack, started_ms: int, expected: int, timeout_s: float = 60) -> list[dict]:
    deadline = time.monotonic() + timeout_s
    rows: list[dict] = []
    while time.monotonic() < deadline:
        rows = httpx.get(
            f"{stack.api_url}/api/v1/poses",
            params={
                "from": started_ms - 1000,
                "to": time.time_ns() // 1_000_000 + 1000,
                "limit": 10000,
            },
            timeout=30,
        ).json()
        if len(rows) >= expected:
            break
        time.sleep(0.5)
    return rows
