"""The VDA 5050 bench workload: schema-valid messages the gateway takes, at its rates, each
counted once the broker acknowledged it (a real Mosquitto; no pipeline)."""

from __future__ import annotations

import time

import pytest

from mapservice.adapters.mqtt_client import make_client
from mapservice.bench.vda_fleet import VdaFleet, iso, vehicle_messages
from mapservice.core.events import decode
from mapservice.core.intake import Intake
from mapservice.ingest.router import Router
from mapservice.local import embedded
from mapservice.settings import Settings


def test_its_messages_are_accepted_by_the_gateway() -> None:
    router = Router(Settings(), gateway_id="bench-test")
    now = time.time_ns() // 1_000_000
    for subtopic, payload in zip(
        ("visualization", "state"), vehicle_messages("v00001", 1, (3.0, 4.0))
    ):
        payload = payload.replace(b"@@TS@@", iso(now))
        record = router.route(f"uagv/v2/VdaBench/v00001/{subtopic}", payload, now, Intake())
        assert record.reason is None, subtopic
        assert decode(record.value).robot_id == "VdaBench:v00001"


def test_each_vehicle_sends_a_state_a_second_and_five_visualizations(tmp_path) -> None:
    if not embedded.mosquitto_installed():
        pytest.fail("mosquitto is not installed (make system-deps installs it)")
    port = embedded.free_port()
    proc = embedded.start_mosquitto(port, tmp_path)
    seen: list[str] = []
    listener = make_client("vda-fleet-listener")
    listener.on_message = lambda _c, _u, m: seen.append(m.topic.rsplit("/", 1)[1])
    listener.connect("127.0.0.1", port)
    listener.subscribe("uagv/#", qos=1)
    listener.loop_start()
    try:
        time.sleep(0.5)
        fleet = VdaFleet(f"mqtt://127.0.0.1:{port}", None, 10, connections=2)
        stats = fleet.run(2.0)
        time.sleep(1.0)
    finally:
        listener.disconnect()
        listener.loop_stop()
        proc.terminate()
        proc.wait(10)
    keys = [(robot, ts) for _, robot, ts, _ in stats.published]
    assert len(keys) == len(set(keys)) == stats.poses  # no two messages of a vehicle share a ms
    # Stamped as sent (a state at most 1 ms after its visualization): the server's
    # publish -> stored timing starts at the stamp, so none may run ahead of its PUBACK.
    ahead_ms = [ts - acked * 1000 for _, _, ts, acked in stats.published]
    assert max(ahead_ms) <= 1, max(ahead_ms)
    assert {robot for robot, _ in keys} == {f"VdaBench:v{i:05d}" for i in range(10)}
    # 2 s: ten visualizations and two states per vehicle
    assert seen.count("visualization") == 100 and seen.count("state") == 20
    assert stats.poses == 120 == fleet.scheduled_events(2.0)
    assert fleet.events_per_robot_s == pytest.approx(6.0)
