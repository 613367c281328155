"""Appendix A of the 2019 documentation, listing by listing, against the real stack.

Requests are sent as a 2019 client sends them: plain HTTP (httpx, JSON bodies as text, no
mapservice code on the client side) and paho-mqtt for the MQTT topics. Reads go without a
credential; writes carry the one change a 2019 robot needs, its writer token
(`Authorization: Bearer`), here the one the stack generated into its data dir as `make up`
does. The stack starts
without a map meta, so the robot start-up sequence runs from the very beginning; the tests
share that one stack and run in file order (each builds on the data of the ones before).
"""

from __future__ import annotations

import base64
import io
import json
import threading
import time
import zlib

import httpx
import numpy as np
import pytest
from PIL import Image

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.adapters.ros_map import load_ros_map, meta_for, slice_chunks
from mapservice.core.wire2019 import (
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
    parse_timestamp,
)
from mapservice.local.stack import Stack
from tests.fixtures.listings_2019 import listing_14, listing_16
from tests.fixtures.paths import MAPS

from .conftest import wait_for_meta
from .test_pipeline import now_ms, publish_all

TOKEN = "contract-admin-token"
CHUNKS = "/api/chunk-service/chunks"
META = "/api/chunk-service/meta"
ROBOTS = "/api/coordinate-service/robots"
DEPOT = load_ros_map(MAPS / "depot.yaml")


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """Brokers, processors + API and the gateway; no map meta published."""
    stack = Stack(
        tmp_path_factory.mktemp("stack-2019"),
        mqtt="mosquitto",
        extra_env={"MAPSERVICE_ADMIN_TOKEN": TOKEN},
    )
    stack.extra_env["MAPSERVICE_PUBLIC_BASE_URL"] = stack.api_url
    with stack.running():
        yield stack


@pytest.fixture(scope="module")
def http(stack):
    """A 2019 client without a credential: reads are open."""
    with httpx.Client(base_url=stack.api_url, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def robot(stack):
    """A 2019 robot with its writer token: the header is all it adds."""
    token = stack.api_secrets().writers[0]
    with httpx.Client(
        base_url=stack.api_url, timeout=60, headers={"Authorization": f"Bearer {token}"}
    ) as client:
        yield client


def until(fetch, done, timeout_s: float = 60, what: str = "condition"):
    """Polls fetch() until done(result); the processors store writes within seconds."""
    deadline = time.monotonic() + timeout_s
    while True:
        result = fetch()
        if done(result):
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}; last: {str(result)[:500]}")
        time.sleep(0.3)


class Subscriber:
    """A paho client listening on one topic, as a 2019 robot or frontend does."""

    def __init__(self, stack: Stack, topic: str) -> None:
        host, port, _ = parse_mqtt_url(stack.mqtt_url)
        self.messages: list[dict] = []
        self._subscribed = threading.Event()
        self.client = make_client(f"contract-sub-{now_ms()}")
        self.client.on_message = lambda _c, _u, msg: self.messages.append(json.loads(msg.payload))
        self.client.on_subscribe = lambda *_args: self._subscribed.set()
        self.client.connect(host, port)
        self.client.loop_start()
        self.client.subscribe(topic, qos=1)
        assert self._subscribed.wait(10), f"no SUBACK for {topic}"

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def check_listing_9(meta: dict) -> None:
    for name in ("width", "height", "CHUNK_WIDTH", "CHUNK_HEIGHT", "CHUNK_ROWS", "CHUNK_COLS"):
        assert type(meta[name]) is int, name
    assert isinstance(meta["comment"], str) and isinstance(meta["max_brightness"], str)


def check_listing_11(body: dict) -> None:
    types = {
        "_index": str,
        "_type": str,
        "_id": str,
        "_version": int,
        "result": str,
        "forced_refresh": bool,
        "_shards": dict,
        "_seq_no": int,
        "_primary_term": int,
    }
    for name, kind in types.items():
        assert type(body[name]) is kind, name
    assert all(type(body["_shards"][k]) is int for k in ("total", "successful", "failed"))
    assert body["result"] == "created"


def check_listing_12(chunk: dict, reduced: bool = False) -> None:
    types = {"row": int, "column": int, "timestamp": str, "id": str, "robotId": str}
    if not reduced:
        types |= {"chunk": str, "type": str}
    assert set(chunk) == set(types)
    for name, kind in types.items():
        assert type(chunk[name]) is kind, name
    assert parse_timestamp(chunk["timestamp"]) is not None
    assert chunk["id"] == f"row:{chunk['row']}_column:{chunk['column']}_{chunk['timestamp']}"


def check_listing_17(pose: dict) -> None:
    assert isinstance(pose["robotId"], str) and parse_timestamp(pose["timestamp"]) is not None
    position, orientation = pose["pose"]["position"], pose["pose"]["orientation"]
    assert all(isinstance(position[k], (int, float)) for k in "xyz")
    assert all(isinstance(orientation[k], (int, float)) for k in "xyzw")
    assert set(pose["status"]) == {"battery", "loaded"}
    assert set(pose["status"]["battery"]) == {"battery_level", "charging"}
    assert pose["_id"] == f"robotId:{pose['robotId']}_{pose['timestamp']}"


def stitched(chunks: list[dict], meta: dict) -> np.ndarray:
    ch, cw = meta["CHUNK_HEIGHT"], meta["CHUNK_WIDTH"]
    canvas = np.zeros((meta["CHUNK_ROWS"] * ch, meta["CHUNK_COLS"] * cw), dtype=np.uint8)
    for c in chunks:
        pixels = np.frombuffer(zlib.decompress(base64.b64decode(c["chunk"])), dtype=np.uint8)
        canvas[c["row"] * ch : (c["row"] + 1) * ch, c["column"] * cw : (c["column"] + 1) * cw] = (
            pixels.reshape(ch, cw)
        )
    return canvas[: meta["height"], : meta["width"]]


# --- the robot start-up sequence (section 5.2 with appendix A) -----------------------------


def test_robot_start_up_sequence(stack, http, robot) -> None:
    """GET meta (404), POST meta, empty map, MQTT upload, second robot downloads it, adverts."""
    # Robot A: no meta stored yet, so it posts its own meta.json (listing 8).
    assert http.get(META).status_code == 404
    meta = meta_for(DEPOT).to_2019()
    r = robot.post(META, content=json.dumps(meta), headers={"Content-Type": "application/json"})
    assert r.status_code == 200, r.text
    check_listing_11(r.json())
    stored = until(lambda: http.get(META), lambda r: r.status_code == 200, what="meta stored")
    check_listing_9(stored.json())
    assert stored.json() == meta
    wait_for_meta(stack)  # the gateway now validates chunks against this grid

    # Advertisements: processors/advertiser.py (Views engineer) publishes them.
    ads = Subscriber(stack, "iot/chunks/advertisement")
    try:
        r = http.get(CHUNKS, params={"latest": "true", "limit": "10000"})
        assert r.status_code == 200 and r.json() == []  # nothing to download yet: upload

        t0 = now_ms() - 5_000
        ts = format_timestamp(t0)
        local = slice_chunks(DEPOT)
        messages = [
            ("iot/chunks/create", encode_chunk_create(row, col, px, ts, "robot-a"))
            for (row, col), px in sorted(local.items())
        ]
        messages += [
            (
                "iot/coordinates/robot-a",
                encode_coordinates(
                    "robot-a",
                    format_timestamp(t0 + k * 1000),
                    1.0 + k,
                    2.0,
                    battery_level=90,
                    loaded=True,
                ),
            )
            for k in range(3)
        ]
        publish_all(stack, messages)

        # Robot B starts: the meta is there, and it downloads the whole map in one query.
        meta_b = http.get(META).json()
        whole = until(
            lambda: http.get(CHUNKS, params={"latest": "true", "limit": "10000"}).json(),
            lambda body: len(body) == len(local),
            what="the whole map",
        )
        for chunk in whole:
            check_listing_12(chunk)
        assert (stitched(whole, meta_b) == DEPOT.pixels).all()

        robots = until(
            lambda: http.get(ROBOTS, params={"latest": "true"}).json(),
            lambda body: any(
                p["robotId"] == "robot-a" and p["timestamp"] == format_timestamp(t0 + 2000)
                for p in body
            ),
            what="robot-a's latest pose",
        )
        [pose] = [p for p in robots if p["robotId"] == "robot-a"]
        check_listing_17(pose)
        assert pose["pose"]["position"]["x"] == 3.0 and pose["status"]["loaded"] is True

        # --- advertisements (listing 15; processors/advertiser.py) -----------------------
        until(
            lambda: len({(a.get("row"), a.get("column")) for a in ads.messages}),
            lambda n: n == len(local),
            what="an advertisement per chunk",
        )
        for ad in ads.messages[:3]:
            assert ad["chunkUrl"].startswith(stack.api_url + "/api/chunk-service/chunks/id/")
            by_url = httpx.get(ad["chunkUrl"], timeout=30)
            assert by_url.status_code == 200
            check_listing_12(by_url.json())
            assert by_url.json()["robotId"] == "robot-a"
            png = httpx.get(ad["chunkUrl"] + "/png", timeout=30)
            assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    finally:
        ads.close()


# --- A.1.2: listings 10 to 13 over REST --------------------------------------------------------


def test_listings_10_11_13_post_a_chunk_and_read_it_back(stack, http, robot) -> None:
    """POST /chunks with listing 10 answers listing 11; the _id then serves listing 13 and a PNG."""
    pixels = bytes(range(100)) * 100
    ts = format_timestamp(now_ms() - 2_000)
    body = listing_14(ts, pixels)
    r = robot.post(CHUNKS, content=json.dumps(body), headers={"Content-Type": "application/json"})
    assert r.status_code == 200, r.text
    check_listing_11(r.json())
    chunk_id = r.json()["_id"]
    assert chunk_id == f"row:3_column:2_{ts}"
    got = until(
        lambda: http.get(f"{CHUNKS}/id/{chunk_id}"),
        lambda r: r.status_code == 200,
        what="the posted chunk",
    )
    check_listing_12(got.json())
    assert got.json()["chunk"] == body["pgmB64compressedData"]
    assert got.json()["type"] == "pgm_base64_compressed" and got.json()["robotId"] == "lkjlkj"
    png = http.get(f"{CHUNKS}/id/{chunk_id}/png")
    assert png.headers["content-type"] == "image/png"
    assert np.asarray(Image.open(io.BytesIO(png.content))).tobytes() == pixels


def test_post_chunk_is_validated_like_mqtt(robot) -> None:
    """A chunk outside the posted meta's grid is a 400 with the MQTT reason code."""
    body = listing_14(format_timestamp(now_ms()), row=99, column=0)
    r = robot.post(CHUNKS, content=json.dumps(body), headers={"Content-Type": "application/json"})
    assert r.status_code == 400 and r.json()["detail"].startswith("out_of_map")


def test_writes_need_the_robot_token_and_json(http, robot) -> None:
    """Without a token a write is 401, with a wrong one 401, as text/plain (even with the token) 415; a meta of another size needs the admin."""
    body = encode_chunk_create(0, 0, bytes(10_000), format_timestamp(now_ms()), "intruder")
    json_type = {"Content-Type": "application/json"}
    assert http.post(CHUNKS, content=body, headers=json_type).status_code == 401
    r = http.post(CHUNKS, content=body, headers={**json_type, "Authorization": "Bearer guessed"})
    assert r.status_code == 401
    r = robot.post(CHUNKS, content=body, headers={"Content-Type": "text/plain"})
    assert r.status_code == 415
    small = {**meta_for(DEPOT).to_2019(), "CHUNK_WIDTH": 10, "CHUNK_HEIGHT": 10}
    small.update(CHUNK_ROWS=-(-small["height"] // 10), CHUNK_COLS=-(-small["width"] // 10))
    r = robot.post(META, content=json.dumps(small), headers=json_type)
    assert r.status_code == 403 and "MAPSERVICE_ADMIN_TOKEN" in r.json()["detail"]


def test_listing_12_query_parameters(http) -> None:
    """GET /chunks: default shape, filters, sort, reduced, type=png, limit/skip, latest at T."""
    default = http.get(CHUNKS).json()
    assert 1 <= len(default) <= 10
    for chunk in default:
        check_listing_12(chunk)
    times = [parse_timestamp(c["timestamp"]) for c in default]
    assert times == sorted(times, reverse=True)  # timestamp:desc by default

    one = http.get(CHUNKS, params={"row": "3", "column": "2", "robotId": "lkjlkj"}).json()
    assert [(c["row"], c["column"], c["robotId"]) for c in one] == [(3, 2, "lkjlkj")]
    assert (
        http.get(
            CHUNKS, params={"timestamp": one[0]["timestamp"], "row": "3", "column": "2"}
        ).json()[0]["id"]
        == one[0]["id"]
    )
    reduced = http.get(CHUNKS, params={"reduced": "true", "limit": "2"}).json()
    for chunk in reduced:
        check_listing_12(chunk, reduced=True)
    [as_png] = http.get(
        CHUNKS, params={"type": "png", "row": "3", "column": "2", "robotId": "lkjlkj"}
    ).json()
    assert as_png["type"] == "png"
    assert Image.open(io.BytesIO(base64.b64decode(as_png["chunk"]))).size == (100, 100)

    asc = http.get(CHUNKS, params={"sort": "row:asc,column:asc", "limit": "5"}).json()
    assert [(c["row"], c["column"]) for c in asc] == sorted((c["row"], c["column"]) for c in asc)
    page = http.get(CHUNKS, params={"limit": "3", "skip": "2"}).json()
    assert [c["id"] for c in page] == [
        c["id"] for c in http.get(CHUNKS, params={"limit": "5"}).json()[2:5]
    ]

    # The complete map just before the REST write of row 3, column 2: robot-a's chunk there.
    before = http.get(
        CHUNKS,
        params={"latest": "true", "updatedBefore": one[0]["timestamp"], "row": "3", "column": "2"},
    ).json()
    assert [c["robotId"] for c in before] == ["robot-a"]
    since = http.get(CHUNKS, params={"updatedSince": one[0]["timestamp"], "limit": "100"}).json()
    assert {c["robotId"] for c in since} == {"lkjlkj"}


def test_bad_and_unknown_parameters(http) -> None:
    """A malformed sort is a 400 with a message; unknown parameters are ignored."""
    r = http.get(CHUNKS, params={"sort": "timestamp:desc; DROP TABLE chunk_events"})
    assert r.status_code == 400 and "sort" in r.json()["detail"]
    r = http.get(ROBOTS, params={"limit": "100000"})
    assert r.status_code == 400 and "limit" in r.json()["detail"]
    assert (
        http.get(CHUNKS, params={"limit": "2", "colour": "red"}).json()
        == http.get(CHUNKS, params={"limit": "2"}).json()
    )


# --- A.2: listings 16 and 17 ------------------------------------------------------------------


def test_listings_16_17_coordinates(stack, http) -> None:
    """Listing 16 over MQTT comes back as listing 17; latest+updatedBefore is the pose at T."""
    t0 = now_ms() - 10_000
    stamps = [format_timestamp(t0), format_timestamp(t0 + 1000)]
    publish_all(
        stack,
        [
            ("iot/coordinates/blabla", json.dumps(listing_16(ts, x=10 + k)).encode())
            for k, ts in enumerate(stamps)
        ],
    )
    poses = until(
        lambda: http.get(ROBOTS, params={"robotId": "blabla"}).json(),
        lambda body: len(body) == 2,
        what="both poses",
    )
    for pose in poses:
        check_listing_17(pose)
    assert [p["timestamp"] for p in poses] == stamps[::-1]
    assert poses[0]["status"] == {
        "battery": {"battery_level": 3, "charging": "sdf"},
        "loaded": "dfs",
    }
    at = http.get(ROBOTS, params={"latest": "true", "updatedBefore": stamps[1]}).json()
    assert [(p["robotId"], p["pose"]["position"]["x"]) for p in at if p["robotId"] == "blabla"] == [
        ("blabla", 10)
    ]
    asc = http.get(ROBOTS, params={"robotId": "blabla", "sort": "timestamp:asc", "limit": "1"})
    assert [p["timestamp"] for p in asc.json()] == stamps[:1]


# --- administrative deletes (last: they wipe the data) ---------------------------------------


def test_deletes_need_the_admin_token(http, robot) -> None:
    """DELETE /chunks and /meta refuse without the token (401), with a robot's (403), and wipe with it."""
    assert http.delete(CHUNKS).status_code == 401
    assert http.delete(META, headers={"Authorization": "Bearer nope"}).status_code == 401
    assert robot.delete(CHUNKS).status_code == 403
    auth = {"Authorization": f"Bearer {TOKEN}"}
    r = http.delete(CHUNKS, headers=auth)
    assert r.status_code == 200 and r.json()["deleted"] >= 29
    assert http.get(CHUNKS, params={"latest": "true"}).json() == []
    assert http.delete(META, headers=auth).status_code == 200
    assert http.get(META).status_code == 404
