"""Foxglove's own client against a fresh `mapservice up` (reads closed: the reader token):
live, it gets the floor at once and a pose published over MQTT within a second; on the
replay port, each seek to an instant of the loaded history brings the floor and the robots
exactly as /api/v1/map/png?at= and /api/v1/robots?at= read them, and playing at 60x sends
every stored chunk write of the span, none skipped; incidents (live as the processors find
them, on replay those going on at a seek) and VDA 5050 errors come on their channels, valid
against their JSON schemas; and the gate refuses a wrong token,
another site's Origin and one client more than the cap. One `up` for every check."""

from __future__ import annotations

import hashlib
import io
import json
import os
import random
import time

import httpx
import numpy as np
import paho.mqtt.publish as mqtt_publish
import pytest
from PIL import Image
from websockets.sync.client import connect

from mapservice.adapters.mcap_channels import (
    CONFLICT_SCHEMA_NAME,
    CONFLICTS_TOPIC,
    ERRORS_SCHEMA_NAME,
    INCIDENT_SCHEMA_NAME,
    INCIDENTS_TOPIC,
    MAP_CHANGES_TOPIC,
    MAP_TOPIC,
    errors_topic,
    path_topic,
    pose_topic,
    state_topic,
)
from mapservice.core.wire2019 import format_timestamp
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


def png_pixels_digest(png: bytes) -> str:
    """The digest of a foxglove.Grid's data holding this image (its rows bottom up)."""
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("L"))
    return hashlib.sha256(np.flipud(pixels).tobytes()).hexdigest()


def on(event: dict, topic: str) -> bool:
    return event["event"] == "message" and event["topic"] == topic


def all_valid(client: FoxgloveNodeClient) -> None:
    advertised = [e for e in client.events if e["event"] == "advertise"]
    assert advertised and all(e["known"] for e in advertised), advertised
    bad = [e for e in client.messages() if not e["valid"]]
    assert not bad, bad[:3]


def test_live_sends_the_floor_at_once_and_a_mqtt_pose_within_a_second(fox):
    with FoxgloveNodeClient(fox.live, token=fox.token) as client:
        info = client.wait_for(lambda e: e["event"] == "serverInfo", 15)
        assert "playbackControl" not in info["capabilities"]
        grid = client.wait_for(lambda e: on(e, MAP_TOPIC), 15)
        assert grid["msg"]["data_len"] > 0 and grid["msg"]["column_count"] > 0
        robot = f"fox-{random.randrange(10**6)}"
        x, y = round(random.uniform(2, 20), 2), round(random.uniform(2, 20), 2)
        body = {
            "robotId": robot,
            "timestamp": format_timestamp(int(time.time() * 1000)),
            "pose": {
                "position": {"x": x, "y": y, "z": 0},
                "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
            },
            "status": {"battery": {"battery_level": 3, "charging": False}, "loaded": True},
        }
        client.quiet(0.3, 15)
        sent = time.monotonic()
        mqtt_publish.single(
            f"iot/coordinates/{robot}", json.dumps(body), qos=1, port=fox.up.mqtt_port
        )
        pose = client.wait_for(lambda e: on(e, pose_topic(robot)), 10)
        assert (
            pose["msg"]["pose"]["position"]["x"] == x and pose["msg"]["pose"]["position"]["y"] == y
        )
        state = client.wait_for(lambda e: on(e, state_topic(robot)), 5)
        assert state["msg"]["loaded"] is True and state["msg"]["battery_level"] == 3
        assert pose["at"] - sent <= 1.0, f"the pose took {pose['at'] - sent:.2f} s"
        all_valid(client)


def seek(client: FoxgloveNodeClient, at_ms: int) -> list[dict]:
    """The messages a paused seek to `at_ms` brings (until the client is quiet)."""
    before = client.send(op="playback", command="pause", speed=1, seek_ms=at_ms)
    client.wait_for(lambda e: e["event"] == "playbackState" and e["did_seek"], 10, before)
    client.wait_for(lambda e: on(e, MAP_TOPIC) and e["log_ms"] == at_ms, 20, before)
    end = client.quiet(0.5, 20)
    return client.messages(before, end)


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
            messages = seek(client, at_ms)
            grids = [m for m in messages if m["topic"] == MAP_TOPIC and m["log_ms"] == at_ms]
            png = fox.api("/api/v1/map/png", at=at_ms).content
            assert grids[-1]["msg"]["data_sha256"] == png_pixels_digest(png), at_ms
            robots = fox.api("/api/v1/robots", at=at_ms).json()["robots"]
            assert robots, f"no robot at {at_ms}"
            latest = {m["topic"]: m["msg"] for m in messages}
            sent_robots = {t for t in latest if t.endswith("/pose")}
            assert sent_robots == {pose_topic(r["robotId"]) for r in robots}
            for r in robots:
                pose = latest[pose_topic(r["robotId"])]["pose"]
                p, q = pose["position"], pose["orientation"]
                assert [p["x"], p["y"], p["z"]] == r["position"]
                assert [q["x"], q["y"], q["z"], q["w"]] == r["orientation"]
                state = latest[state_topic(r["robotId"])]
                assert (state["battery_level"], state["charging"], state["loaded"]) == (
                    r["battery_level"],
                    r["charging"],
                    r["loaded"],
                )
                path = [
                    [s["position"]["x"], s["position"]["y"]]
                    for s in latest[path_topic(r["robotId"])]["poses"]
                ]
                assert path == (r["path"] or [])
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
        seek(client, first - 1000)
        before = client.send(op="playback", command="play", speed=60)
        time.sleep(4)
        paused = client.send(op="playback", command="pause", speed=60)
        state = client.wait_for(
            lambda e: e["event"] == "playbackState" and e["status"] == 1, 10, paused
        )
        end = client.quiet(0.5, 20)
        played = client.messages(before, end)
        # Every write up to the last instant played was sent (a step sends all of its own).
        reached = max(m["log_ms"] for m in played) + 1
        assert reached >= first + 60_000, "60x for 4 s played less than a minute"
        assert state["current_ms"] >= first + 60_000
        expected = fox.api(
            "/api/v1/chunk-events", **{"from": first - 1000, "to": reached}, limit=100_000
        ).json()
        got = [m["msg"] for m in played if m["topic"] == MAP_CHANGES_TOPIC]
        assert [
            (g["row"], g["column"], g["robot_id"], g["content_hash"], g["ts_ms"]) for g in got
        ] == [
            (e["row"], e["column"], e["robotId"], e["content_hash"], e["ts_ms"]) for e in expected
        ]
        last_grid = [m for m in played if m["topic"] == MAP_TOPIC][-1]
        png = fox.api("/api/v1/map/png", at=last_grid["log_ms"]).content
        assert last_grid["msg"]["data_sha256"] == png_pixels_digest(png)
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
