"""The replay UI draws VDA 5050 vehicles: npm vda-5050-lib's virtual vehicles
(tests/vda5050/fleet.cjs) drive an order against the UI stack's Mosquitto; live mode draws
them as they report, and a seek to an instant of their drive draws each where it said it
was then (the stack has no map transforms: the vehicles' frame is the map's)."""

from __future__ import annotations

import time

import httpx
import pytest

from mapservice.core.vda_ids import robot_id_for
from tests.fixtures.vda5050_fleet import FleetProcess, Recorder, installed_fleet, vda_ms

from .test_replay import TIMEOUT_MS, open_at

FLEET = (("Acme", "ui-1"), ("Robo Co", "ui:2"))


def order(order_id: str, start: tuple[float, float], end: tuple[float, float], map_id: str) -> dict:
    nodes = [{"nodeId": f"{order_id}-{i}", "sequenceId": 2 * i, "released": True,
              "nodePosition": {"x": x, "y": y, "mapId": map_id}, "actions": []}
             for i, (x, y) in enumerate((start, end))]
    return {"orderId": order_id, "orderUpdateId": 0, "nodes": nodes, "edges": [{
        "edgeId": f"{order_id}-e", "sequenceId": 1, "startNodeId": nodes[0]["nodeId"],
        "endNodeId": nodes[1]["nodeId"], "released": True, "actions": []}]}


def test_the_replay_ui_draws_vda_5050_vehicles(page, history_stack, tmp_path) -> None:
    installed_fleet()
    stack = history_stack
    open_at(page, stack, "?live=1")
    page.wait_for_function("() => window.__replay.liveStatus.connected", timeout=TIMEOUT_MS)
    ox, oy = page.evaluate("() => window.__replay.meta")["origin"][:2]
    common = {"broker": stack.mqtt_url, "interface": "uagv", "vdaVersion": "2.0.0"}
    routes = {}
    for i, (m, s) in enumerate(FLEET):
        start = (ox + 8.0 + 4 * i, oy + 8.0)
        routes[m, s] = (start, (start[0] + 3.0, start[1] + 2.0))
    recorder = Recorder(stack.mqtt_port)
    vehicles = []
    try:
        for (m, s), (start, _) in routes.items():
            vehicles.append(FleetProcess("vehicle", {
                **common, "manufacturer": m, "serialNumber": s, "batteryCharge": 70,
                "initialPosition": {"mapId": "floor", "x": start[0], "y": start[1], "theta": 0},
                "speed": 1.0, "timeLapse": 1, "visualizationMs": 200,
            }, tmp_path, f"ui-{s}".replace(":", "_")))
        for v in vehicles:
            v.wait_for("started", 30)
        master = FleetProcess("master", {**common, "plans": [
            {"agv": {"manufacturer": m, "serialNumber": s},
             "orders": [order(f"ui-{i}", *routes[m, s], "floor")]}
            for i, (m, s) in enumerate(FLEET)]}, tmp_path, "ui-master")
        # Live: both vehicles drawn while they drive.
        ids = [robot_id_for(m, s) for m, s in FLEET]
        page.wait_for_function(
            "(ids) => ids.every(id => window.__replay.drawnRobots().some(r => r.robotId === id))",
            arg=ids, timeout=TIMEOUT_MS)
        master.wait_for("done", 60)
        master.stop()
    finally:
        for v in vehicles:
            v.stop()
        recorder.stop()

    # A seek to the middle of the drive: each vehicle where its last message before said.
    positions = {robot_id_for(m, s): [(vda_ms(msg["timestamp"]), msg["agvPosition"])
                                      for _, msg in recorder.of("visualization", m, s)]
                 for m, s in FLEET}
    t = min(p[len(p) // 2][0] for p in positions.values())
    for rid, reported in positions.items():
        wait_until_stored(stack, rid, reported[-1][0])
    page.goto("about:blank")
    open_at(page, stack, f"?t={t}")
    page.evaluate("() => window.__replay.fitGrid()")
    shown = {r["robotId"]: r for r in page.evaluate("() => window.__replay.robots()")}
    for rid, reported in positions.items():
        ts, pos = [(ts, pos) for ts, pos in reported if ts <= t][-1]
        assert shown[rid]["ts_ms"] >= ts  # a state may be later, at the same position
        assert shown[rid]["x"] == pytest.approx(pos["x"], abs=0.0011)  # stored in mm
        assert shown[rid]["y"] == pytest.approx(pos["y"], abs=0.0011)
    page.wait_for_function(
        "(ids) => ids.every(id => window.__replay.drawnRobots().some(r => r.robotId === id))",
        arg=ids, timeout=TIMEOUT_MS)
    drawn = {d["robotId"]: d for d in page.evaluate("() => window.__replay.drawnRobots()")}
    for rid in ids:
        at = page.evaluate("([x, y]) => window.__replay.screenPointOfMetres(x, y)",
                           [shown[rid]["x"], shown[rid]["y"]])
        assert abs(drawn[rid]["x"] - at["x"]) <= 0.5 and abs(drawn[rid]["y"] - at["y"]) <= 0.5
    assert not page.errors


def wait_until_stored(stack, robot_id: str, last_ms: int, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        rows = httpx.get(f"{stack.api_url}/api/v1/poses", params={
            "robotId": robot_id, "from": last_ms, "to": last_ms + 1}, timeout=30).json()
        if rows:
            return
        time.sleep(0.5)
    raise AssertionError(f"{robot_id}'s last pose was never stored")
