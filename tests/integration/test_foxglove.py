"""Foxglove's own client against a fresh `mapservice up` (reads closed: the reader token):
live, it gets the floor at once and a pose published over MQTT within a second; on the
replay port, each seek to an instant of the loaded history brings the floor and the robots
exactly as /api/v1/map/png?at= and /api/v1/robots?at= read them, and playing at 60x sends
every stored chunk write of the span, none skipped; incidents (live as the processors find
them, on replay those going on at a seek) and VDA 5050 errors come on their channels, valid
against their JSON schemas; and the gate refuses a wrong token,
another site's Origin and one client more than the cap. One `up` for every check."""

from __future__ import annotations

import json
import os
import random
import time

import httpx
import paho.mqtt.publish as mqtt_publish
import pytest
from websockets.sync.client import connect

from mapservice.adapters.mcap_channels import (
    CONFLICT_SCHEMA_NAME,
    CONFLICTS_TOPIC,
    ERRORS_SCHEMA_NAME,
    INCIDENT_SCHEMA_NAME,
    INCIDENTS_TOPIC,
    MAP_TOPIC,
    errors_topic,
)
from mapservice.core.wire2019 import format_timestamp
from tests.fixtures.foxglove_checks import (
    all_valid,
    assert_a_seek_brings_what_the_api_reads,
    assert_live_sends_the_floor_and_a_mqtt_pose_within_a_second,
    assert_playing_sends_every_stored_chunk_write,
    on,
    seek,
)
from tests.fixtures.foxglove_client import FoxgloveNodeClient
from tests.fixtures.up import UP_ENV, Up

pytestmark = [pytest.mark.integration]

MAX_CLIENTS = 3


class Fox:
    def __init__(self, up: Up, token: str) -> None:
        self.up, self.token = up, token
        self.live = f"ws://127.0.0.1:{up.foxglove_port}/"
        self.replay = f"ws://127.0.0.1:{up.foxglove_port}/replay"
        self.http = httpx.Client(
            base_url=up.api_url, headers={"Authorization": f"Bearer {token}"}, timeout=30
        )

    def api(self, path: str, **params) -> httpx.Response:
        response = self.http.get(path, params=params)
        response.raise_for_status()
        return response


@pytest.fixture(scope="module")
def fox(tmp_path_factory):
    data = tmp_path_factory.mktemp("foxglove") / "data"
    env = {
        **os.environ,
        **UP_ENV,
        "MAPSERVICE_API_READ_ACCESS": "token",
        "MAPSERVICE_FOXGLOVE_MAX_CLIENTS": str(MAX_CLIENTS),
    }
    up = Up(data, "--robots", "1", "--history-days", "0.01", env=env)
    try:
        yield Fox(up, (data / "secrets" / "reader-token").read_text().strip())
    finally:
        up.stop()


def test_live_sends_the_floor_at_once_and_a_mqtt_pose_within_a_second(fox):
    with FoxgloveNodeClient(fox.live, token=fox.token) as client:
        assert_live_sends_the_floor_and_a_mqtt_pose_within_a_second(client, fox.up.mqtt_port)


def test_seeks_bring_the_floor_and_robots_the_api_reads(fox):
    history = fox.api(
        "/api/v1/chunk-events",
        **{"from": int(time.time() * 1000) - 86_400_000, "to": int(time.time() * 1000)},
    ).json()
    assert history, "the loaded history holds no chunk write"
    now = int(time.time() * 1000)
    instants = sorted(now - random.randrange(60_000, 13 * 60_000) for _ in range(3))
    with FoxgloveNodeClient(fox.replay, token=fox.token) as client:
        info = client.wait_for(lambda e: e["event"] == "serverInfo", 15)
        assert "playbackControl" in info["capabilities"]
        start, end = (
            int(info["dataStartTime"]["sec"]) * 1000,
            int(info["dataEndTime"]["sec"]) * 1000,
        )
        assert abs(end - now) < 60_000 and end - start == pytest.approx(7 * 86_400_000, abs=2000)
        client.quiet(0.5, 20)
        for at_ms in instants:
            assert_a_seek_brings_what_the_api_reads(client, fox.api, at_ms)
        all_valid(client)


def test_playing_at_60x_sends_every_stored_chunk_write(fox):
    now = int(time.time() * 1000)
    writes = fox.api(
        "/api/v1/chunk-events", **{"from": now - 86_400_000, "to": now}, limit=100_000
    ).json()
    first = writes[0]["ts_ms"]
    with FoxgloveNodeClient(fox.replay, token=fox.token) as client:
        client.wait_for(lambda e: e["event"] == "serverInfo", 15)
        client.quiet(0.5, 20)
        played = assert_playing_sends_every_stored_chunk_write(client, fox.api, first - 1000, 60, 4)
        assert played >= 1
        all_valid(client)


def low_battery_pose(fox: Fox, robot: str, ts_ms: int) -> None:
    """A 2019 pose of `robot` with 3 % battery, not charging: a battery_low incident."""
    body = {
        "robotId": robot,
        "timestamp": format_timestamp(ts_ms),
        "pose": {
            "position": {"x": 4.0, "y": 5.0, "z": 0},
            "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
        },
        "status": {"battery": {"battery_level": 3, "charging": False}, "loaded": False},
    }
    mqtt_publish.single(f"iot/coordinates/{robot}", json.dumps(body), qos=1, port=fox.up.mqtt_port)


def test_live_sends_each_incident_found_and_vda_errors_on_their_channels(fox):
    """A robot reporting a low battery: its battery_low incident on /incidents as the
    processors announce it; a VDA 5050 vehicle's state with errors on its errors channel
    (re-read from the store within MAPSERVICE_FOXGLOVE_ANNOTATIONS_EVERY_S); /conflicts
    advertised with its schema. Every message valid against its channel's JSON schema."""
    from tests.fixtures import vda5050 as vda

    with FoxgloveNodeClient(fox.live, token=fox.token) as client:
        client.wait_for(lambda e: on(e, MAP_TOPIC), 15)
        advertised = {e["topic"]: e["schema"] for e in client.events if e["event"] == "advertise"}
        assert advertised[INCIDENTS_TOPIC] == INCIDENT_SCHEMA_NAME
        assert advertised[CONFLICTS_TOPIC] == CONFLICT_SCHEMA_NAME
        robot = f"fox-low-{random.randrange(10**6)}"
        low_battery_pose(fox, robot, int(time.time() * 1000))
        found = client.wait_for(
            lambda e: on(e, INCIDENTS_TOPIC) and robot in e["msg"]["robots"], 30
        )
        assert found["valid"] and found["msg"]["kind"] == "battery_low", found
        assert found["msg"]["event"] == "start" and found["msg"]["end_ms"] is None
        now = int(time.time() * 1000)
        listed = fox.api("/api/v1/incidents", **{"from": now - 86_400_000, "to": now + 1})
        assert found["msg"]["id"] in {i["id"] for i in listed.json()["incidents"]}
        serial = str(random.randrange(10**6))
        state = vda.state(
            "2.0.0",
            "FoxAcme",
            serial,
            int(time.time() * 1000),
            errors=(("FATAL", "bumper", "hit"), ("WARNING", "lowBattery", "charge me")),
        )
        mqtt_publish.single(
            f"uagv/v2/FoxAcme/{serial}/state", vda.encode(state), qos=1, port=fox.up.mqtt_port
        )
        errors = client.wait_for(lambda e: on(e, errors_topic(f"FoxAcme:{serial}")), 30)
        assert errors["schema"] == ERRORS_SCHEMA_NAME and errors["valid"], errors
        assert (errors["msg"]["count"], errors["msg"]["fatal"]) == (2, 1)
        all_valid(client)


def going_on_at(fox: Fox, at_ms: int) -> set[str]:
    """The incidents the API lists as going on at `at_ms` (begun, not ended before it)."""
    listed = fox.api("/api/v1/incidents", **{"from": at_ms, "to": at_ms + 1}).json()
    return {i["id"] for i in listed["incidents"] if i["start_ms"] <= at_ms}


def test_a_replay_seek_brings_the_incidents_going_on_then(fox):
    """Seeks to an incident's start and to instants of the history: /incidents holds the
    incidents the API lists as going on at that instant (begun, not yet ended), each valid."""
    robot = f"fox-seek-{random.randrange(10**6)}"
    low_battery_pose(fox, robot, int(time.time() * 1000) - 2000)
    now = int(time.time() * 1000)

    def listed() -> list[dict]:
        return fox.api(
            "/api/v1/incidents", **{"from": now - 86_400_000, "to": now + 60_000}
        ).json()["incidents"]

    deadline = time.monotonic() + 30
    while not any(robot in i["robots"] for i in listed()):
        assert time.monotonic() < deadline, "no battery_low incident stored"
        time.sleep(0.5)
    time.sleep(1.5)  # the replay's window ends at its connect: after the incident's start
    ours = next(i for i in listed() if robot in i["robots"])
    starts = [i["start_ms"] for i in listed()]
    instants = [ours["start_ms"], *sorted(random.sample(starts, min(2, len(starts))))]
    with FoxgloveNodeClient(fox.replay, token=fox.token) as client:
        client.wait_for(lambda e: e["event"] == "serverInfo", 15)
        client.quiet(0.5, 20)
        for at_ms in instants:
            # The live detection moves an ongoing incident's stored end on while the test
            # runs: the API is asked before and after the seek, and what changed in between
            # may go either way.
            before = going_on_at(fox, at_ms)
            messages = seek(client, at_ms)
            after = going_on_at(fox, at_ms)
            got = {m["msg"]["id"] for m in messages if m["topic"] == INCIDENTS_TOPIC}
            assert before & after <= got <= before | after, at_ms
        assert ours["id"] in {
            m["msg"]["id"] for m in client.messages() if m["topic"] == INCIDENTS_TOPIC
        }
        all_valid(client)


def test_a_wrong_token_another_origin_and_one_client_too_many_are_refused(fox):
    cases = {
        "wrong token": ({"token": "not-" + fox.token}, 401),
        "no token": ({}, 401),
        "another site's page": ({"token": fox.token, "origin": "https://evil.example"}, 403),
    }
    for name, (kwargs, status) in cases.items():
        with FoxgloveNodeClient(fox.live, **kwargs) as client:
            refused = client.wait_for(lambda e: e["event"] in ("refused", "serverInfo"), 15)
            assert (refused["event"], refused.get("status")) == ("refused", status), name
    held = [
        connect(
            fox.live,
            subprotocols=["foxglove.websocket.v1"],
            additional_headers={"Authorization": f"Bearer {fox.token}"},
            open_timeout=10,
        )
        for _ in range(MAX_CLIENTS)
    ]
    try:
        with FoxgloveNodeClient(fox.live, token=fox.token) as client:
            refused = client.wait_for(lambda e: e["event"] in ("refused", "serverInfo"), 15)
            assert refused.get("status") == 503 and "MAX_CLIENTS" in refused["body"]
    finally:
        for ws in held:
            ws.close()
    with FoxgloveNodeClient(fox.live, token=fox.token) as client:
        client.wait_for(lambda e: e["event"] == "serverInfo", 15)
