"""The replay UI draws VDA 5050 vehicles: npm vda-5050-lib's virtual vehicles
(tests/vda5050/fleet.cjs) drive an order against the UI stack's Mosquitto; live mode draws
them as they report, and a seek to an instant of their drive draws each where it said it
was then (the stack has no map transforms: the vehicles' frame is the map's). A Python
vehicle raises and clears errors and loses its connection: the timeline marks where each
error began, the fleet panel shows its errors and its exact offline instant, its details
its factsheet."""

from __future__ import annotations

import time
from datetime import UTC, datetime

import httpx
import pytest

from mapservice.adapters.mqtt_client import make_client
from mapservice.core.vda_ids import robot_id_for
from tests.fixtures import vda5050 as vda
from tests.fixtures.vda5050_fleet import FleetProcess, Recorder, installed_fleet, vda_ms

from .test_investigator import screenshot
from .test_replay import TIMEOUT_MS, open_at

FLEET = (("Acme", "ui-1"), ("Robo Co", "ui:2"))


def order(order_id: str, start: tuple[float, float], end: tuple[float, float], map_id: str) -> dict:
    nodes = [
        {
            "nodeId": f"{order_id}-{i}",
            "sequenceId": 2 * i,
            "released": True,
            "nodePosition": {"x": x, "y": y, "mapId": map_id},
            "actions": [],
        }
        for i, (x, y) in enumerate((start, end))
    ]
    return {
        "orderId": order_id,
        "orderUpdateId": 0,
        "nodes": nodes,
        "edges": [
            {
                "edgeId": f"{order_id}-e",
                "sequenceId": 1,
                "startNodeId": nodes[0]["nodeId"],
                "endNodeId": nodes[1]["nodeId"],
                "released": True,
                "actions": [],
            }
        ],
    }


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
            vehicles.append(
                FleetProcess(
                    "vehicle",
                    {
                        **common,
                        "manufacturer": m,
                        "serialNumber": s,
                        "batteryCharge": 70,
                        "initialPosition": {
                            "mapId": "floor",
                            "x": start[0],
                            "y": start[1],
                            "theta": 0,
                        },
                        "speed": 1.0,
                        "timeLapse": 1,
                        "visualizationMs": 200,
                    },
                    tmp_path,
                    f"ui-{s}".replace(":", "_"),
                )
            )
        for v in vehicles:
            v.wait_for("started", 30)
        master = FleetProcess(
            "master",
            {
                **common,
                "plans": [
                    {
                        "agv": {"manufacturer": m, "serialNumber": s},
                        "orders": [order(f"ui-{i}", *routes[m, s], "floor")],
                    }
                    for i, (m, s) in enumerate(FLEET)
                ],
            },
            tmp_path,
            "ui-master",
        )
        # Live: both vehicles drawn while they drive.
        ids = [robot_id_for(m, s) for m, s in FLEET]
        page.wait_for_function(
            "(ids) => ids.every(id => window.__replay.drawnRobots().some(r => r.robotId === id))",
            arg=ids,
            timeout=TIMEOUT_MS,
        )
        master.wait_for("done", 60)
        master.stop()
    finally:
        for v in vehicles:
            v.stop()
        recorder.stop()

    # A seek to the middle of the drive: each vehicle where its last message before said.
    positions = {
        robot_id_for(m, s): [
            (vda_ms(msg["timestamp"]), msg["agvPosition"])
            for _, msg in recorder.of("visualization", m, s)
        ]
        for m, s in FLEET
    }
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
        arg=ids,
        timeout=TIMEOUT_MS,
    )
    drawn = {d["robotId"]: d for d in page.evaluate("() => window.__replay.drawnRobots()")}
    for rid in ids:
        at = page.evaluate(
            "([x, y]) => window.__replay.screenPointOfMetres(x, y)",
            [shown[rid]["x"], shown[rid]["y"]],
        )
        assert abs(drawn[rid]["x"] - at["x"]) <= 0.5 and abs(drawn[rid]["y"] - at["y"]) <= 0.5
    assert not page.errors


def wait_until_stored(stack, robot_id: str, last_ms: int, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        rows = httpx.get(
            f"{stack.api_url}/api/v1/poses",
            params={"robotId": robot_id, "from": last_ms, "to": last_ms + 1},
            timeout=30,
        ).json()
        if rows:
            return
        time.sleep(0.5)
    raise AssertionError(f"{robot_id}'s last pose was never stored")


def now_ms() -> int:
    return time.time_ns() // 1_000_000


def iso(ms: int) -> str:
    return datetime.fromtimestamp(ms / 1000, UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def connected_vehicle(stack, v: str, m: str, s: str):
    """A VDA 5050 vehicle's MQTT client, connected, whose last will says its connection
    broke (as a vehicle's broker announces it); and its topics' base."""
    client = make_client(f"vda-{m}-{s}-{now_ms()}")
    base = f"uagv/v2/{m}/{s}"
    client.will_set(
        f"{base}/connection",
        vda.encode(vda.connection(v, m, s, now_ms(), "CONNECTIONBROKEN")),
        qos=1,
        retain=True,
    )
    client.connect("127.0.0.1", stack.mqtt_port)
    client.loop_start()
    return client, base


def test_vda_errors_connection_and_factsheet_in_the_replay(page, history_stack) -> None:
    """One vehicle: online, a factsheet, a state with a FATAL and a WARNING error (the
    mark's hover names level, type and description), the same again, a state that clears
    them, then a broken connection (its broker's last will). The fleet row and the details
    show the errors at the playhead, none after the clear, and offline from the break."""
    stack = history_stack
    v, m, s = "2.1.0", "Acme", "ui-err"
    rid = robot_id_for(m, s)
    open_at(page, stack, "?live=1")
    ox, oy = page.evaluate("() => window.__replay.meta")["origin"][:2]
    x, y = ox + 14.0, oy + 9.0
    client, base = connected_vehicle(stack, v, m, s)

    def publish(sub: str, msg: dict) -> None:
        client.publish(f"{base}/{sub}", vda.encode(msg), qos=1).wait_for_publish(10)

    sheet = vda.factsheet(v, m, s, now_ms())
    sheet["typeSpecification"]["seriesName"] = "Tugger 3"
    sheet["physicalParameters"]["speedMax"] = 1.8
    publish("connection", vda.connection(v, m, s, now_ms(), "ONLINE"))
    publish("factsheet", sheet)
    errors = (("FATAL", "bumper", "hit"), ("WARNING", "lowBattery", "charge me"))
    times = []
    for i, errs in enumerate(((), errors, errors, ())):
        times.append(now_ms())
        publish("state", vda.state(v, m, s, times[-1], x=x + i, y=y, errors=errs))
        time.sleep(0.4)
    client.loop_stop()
    client.socket().close()  # the connection breaks: the broker publishes the last will
    broke_after = now_ms()
    deadline = time.monotonic() + 60
    while True:
        facts = httpx.get(f"{stack.api_url}/api/v1/robots/{rid}/vda5050", timeout=30).json()
        if [c["state"] for c in facts["connections"]] == ["ONLINE", "CONNECTIONBROKEN"] and facts[
            "errorClears"
        ] == [times[3]]:
            break
        assert time.monotonic() < deadline, facts
        time.sleep(0.5)
    broke = facts["connections"][1]["ts_ms"]
    assert broke >= broke_after - 50

    span = f"{iso(times[0] - 60_000)},{iso(broke + 60_000)}"
    open_at(page, stack, f"?t={times[2]}&sel={rid}&panels=fleet&span={span}")
    marks = page.locator(f'[data-testid="error-mark"][data-robot="{rid}"]')
    marks.first.wait_for(timeout=TIMEOUT_MS)
    assert sorted(
        (marks.nth(i).get_attribute("data-ts"), marks.nth(i).get_attribute("data-level"))
        for i in range(marks.count())
    ) == [(str(times[1]), "FATAL"), (str(times[1]), "WARNING")]
    box = marks.first.bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    hover = page.get_by_test_id("timeline-error-hover")
    hover.wait_for(timeout=TIMEOUT_MS)
    assert f"{rid}: FATAL bumper: hit" in hover.inner_text()
    assert f"{rid}: WARNING lowBattery: charge me" in hover.inner_text()
    assert (
        "FATAL bumper: hit"
        in marks.first.locator("title").text_content()
        + marks.nth(1).locator("title").text_content()
    )

    row = page.locator(f'[data-testid="fleet-row"][data-robot="{rid}"]')
    row_errors = page.locator(f'[data-testid="fleet-errors"][data-robot="{rid}"] .err')
    row_errors.first.wait_for(timeout=TIMEOUT_MS)
    assert row_errors.all_inner_texts() == ["FATAL bumper: hit", "WARNING lowBattery: charge me"]
    assert row.get_by_test_id("fleet-online").inner_text() == "online"
    sheet_text = page.get_by_test_id("details-factsheet")
    sheet_text.wait_for(timeout=TIMEOUT_MS)
    for part in ("Acme", "serial ui-err", "series Tugger 3", "max speed 1.8 m/s", "2.1.0"):
        assert part in sheet_text.inner_text(), part
    assert "FATAL bumper: hit" in page.get_by_test_id("details-errors").inner_text()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    screenshot(page, "ui-vda-errors.png")

    # After the clearing state: no errors in the row or the details.
    page.goto("about:blank")
    open_at(page, stack, f"?t={times[3]}&sel={rid}&panels=fleet&span={span}")
    page.wait_for_function(
        "(id) => document.querySelector(`[data-testid=details-errors]`)?.innerText.includes('none')",
        arg=rid,
        timeout=TIMEOUT_MS,
    )
    assert (
        row.count() == 1
        and page.locator(f'[data-testid="fleet-errors"][data-robot="{rid}"]').count() == 0
    )
    # One millisecond before the break it is online; at the break, offline.
    for t, shown in ((broke - 1, "online"), (broke, "offline (broken)")):
        page.goto("about:blank")
        open_at(page, stack, f"?t={t}&sel={rid}&panels=fleet&span={span}")
        page.wait_for_function(
            "([id, shown]) => document.querySelector(`[data-testid=fleet-row][data-robot='${id}'] "
            "[data-testid=fleet-online]`)?.innerText === shown",
            arg=[rid, shown],
            timeout=TIMEOUT_MS,
        )
    assert "CONNECTIONBROKEN" in page.get_by_test_id("details-online").inner_text()
    assert not page.errors


def test_the_details_agree_with_the_fleet_row_before_the_vehicle_s_own_facts_arrive(
    page, history_stack
) -> None:
    """The details read the selected vehicle's facts apart from the fleet row's; until they
    arrive (here: never, the request fails) the details show the fleet's exact connection
    state, not "online" from the pose silence beside a row that says "offline (broken)"."""
    stack = history_stack
    v, m, s = "2.1.0", "Acme", "ui-late"
    rid = robot_id_for(m, s)
    open_at(page, stack, "?live=1")
    ox, oy = page.evaluate("() => window.__replay.meta")["origin"][:2]
    client, base = connected_vehicle(stack, v, m, s)
    for sub, msg in (
        ("connection", vda.connection(v, m, s, now_ms(), "ONLINE")),
        ("state", vda.state(v, m, s, now_ms(), x=ox + 16.0, y=oy + 9.0, errors=())),
    ):
        client.publish(f"{base}/{sub}", vda.encode(msg), qos=1).wait_for_publish(10)
    client.loop_stop()
    client.socket().close()  # the broker publishes the last will
    deadline = time.monotonic() + 60
    while True:
        facts = httpx.get(f"{stack.api_url}/api/v1/robots/{rid}/vda5050", timeout=30).json()
        if [c["state"] for c in facts["connections"]] == ["ONLINE", "CONNECTIONBROKEN"]:
            break
        assert time.monotonic() < deadline, facts
        time.sleep(0.5)
    broke = facts["connections"][1]["ts_ms"]

    own = f"/api/v1/robots/{rid.replace(':', '%3A')}/vda5050"
    refused = []

    def refuse(route) -> None:
        refused.append(route.request.url)
        route.abort()

    page.goto("about:blank")
    page.route(lambda url: own in url, refuse)
    span = f"{iso(broke - 60_000)},{iso(broke + 60_000)}"
    open_at(page, stack, f"?t={broke}&sel={rid}&panels=fleet&span={span}")
    page.wait_for_function(
        "(id) => document.querySelector(`[data-testid=fleet-row][data-robot='${id}'] "
        "[data-testid=fleet-online]`)?.innerText === 'offline (broken)'",
        arg=rid,
        timeout=TIMEOUT_MS,
    )
    assert refused, "the page never asked for the vehicle's own facts"
    assert "CONNECTIONBROKEN" in page.get_by_test_id("details-online").inner_text()
