"""The 2019 chunk service (appendix A.1), its writes: meta (A.1.1, listing 9) and POST
/chunks (listings 10, 11), over a SpyStore and an in-memory event log."""

from __future__ import annotations

import base64
import json
import zlib

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.events import ChunkUpdated, MapMetaSet, decode
from mapservice.core.intake import Intake
from mapservice.ingest.router import Router
from mapservice.testing.memory_publisher import MemoryPublisher
from tests.api.chunk_service_kit import (
    ADMIN,
    BASE,
    CLOCK_MS,
    JSON,
    WRITER,
    anonymous,
)

# isort: split
from tests.api.chunk_service_kit import client, publisher, settings, store  # noqa: F401  (fixtures)
from tests.fixtures.legacy import SpyStore, process

# --- meta (A.1.1, listing 9) -----------------------------------------------------------------


def test_get_meta_has_listing_9_fields_and_types(client) -> None:
    """GET /meta returns meta.json with the fields and JSON types of listing 9."""
    r = client.get(f"{BASE}/meta")
    assert r.status_code == 200
    meta = r.json()
    for name in ("width", "height", "CHUNK_WIDTH", "CHUNK_HEIGHT", "CHUNK_ROWS", "CHUNK_COLS"):
        assert type(meta[name]) is int, name
    assert isinstance(meta["comment"], str) and meta["max_brightness"] == "255"
    assert (meta["CHUNK_ROWS"], meta["CHUNK_COLS"], meta["width"]) == (4, 5, 500)


def test_get_meta_without_meta_is_404(settings) -> None:
    """Without a stored meta GET /meta is a 404 telling the robot to POST one."""
    client = TestClient(create_app(settings, SpyStore(), {}, ManualClock(CLOCK_MS)))
    r = client.get(f"{BASE}/meta")
    assert r.status_code == 404 and "POST" in r.json()["detail"]


META_8 = {
    "comment": "# CREATOR: GIMP PNM Filter Version 1.1",
    "width": 4800,
    "height": 3200,
    "max_brightness": "255",
    "CHUNK_WIDTH": 100,
    "CHUNK_HEIGHT": 100,
    "CHUNK_ROWS": 32,
    "CHUNK_COLS": 48,
}


def test_post_meta_goes_through_the_meta_topic(client, store, publisher, settings) -> None:
    """POST /meta publishes a map.meta_set event on the meta topic; once stored, GET returns it."""
    r = client.post(f"{BASE}/meta", json=META_8, headers=ADMIN)
    assert r.status_code == 200, r.text
    assert r.json()["result"] == "created" and r.json()["_index"] == "meta"
    publisher.poll()
    [(key, value)] = publisher.records[settings.topic_meta_events]
    env = decode(value)
    assert key == b"map" and isinstance(env.payload, MapMetaSet)
    assert env.event_time_ms == CLOCK_MS
    assert client.get(f"{BASE}/meta").json()["CHUNK_ROWS"] == 4  # not stored yet
    process(publisher, store)
    assert client.get(f"{BASE}/meta").json() == META_8


def test_put_meta_is_post_meta(client, store, publisher) -> None:
    """PUT /meta (section A.1.1: robots "POSTS/PUTS" it) stores the meta like POST."""
    assert client.put(f"{BASE}/meta", json=META_8, headers=ADMIN).status_code == 200
    assert process(publisher, store) == 1
    assert client.get(f"{BASE}/meta").json() == META_8


def test_changing_the_map_geometry_needs_the_admin_token(client, publisher) -> None:
    """A meta of another size is 403 with a robot's token, 401 without or with a wrong one; nothing is published."""
    r = client.post(f"{BASE}/meta", json=META_8)
    assert r.status_code == 403 and "MAPSERVICE_ADMIN_TOKEN" in r.json()["detail"]
    assert "500 x 400 px" in r.json()["detail"]
    assert anonymous(client).put(f"{BASE}/meta", json=META_8).status_code == 401
    assert (
        client.put(
            f"{BASE}/meta", json=META_8, headers={"Authorization": "Bearer nope"}
        ).status_code
        == 401
    )
    publisher.poll()
    assert not publisher.records


def test_same_geometry_and_first_meta_need_a_writer_token(
    client, store, publisher, settings
) -> None:
    """Re-posting the held geometry (a 2019 robot's start-up) and the very first meta need a writer token, not the admin's."""
    same = {**META_8, "width": 500, "height": 400, "CHUNK_ROWS": 4, "CHUNK_COLS": 5}
    assert client.post(f"{BASE}/meta", json=same).status_code == 200
    assert anonymous(client).post(f"{BASE}/meta", json=same).status_code == 401
    empty = TestClient(
        create_app(settings, SpyStore(), {}, ManualClock(CLOCK_MS), publisher=publisher),
        headers=WRITER,
    )
    assert empty.post(f"{BASE}/meta", json=META_8).status_code == 200


@pytest.mark.parametrize("path, body", [("meta", json.dumps(META_8)), ("chunks", "{}")])
@pytest.mark.parametrize(
    "content_type",
    ["text/plain", "application/x-www-form-urlencoded", "multipart/form-data; boundary=x", None],
)
def test_writes_take_json_bodies_only(client, publisher, path, body, content_type) -> None:
    """A write sent as text/plain or a form (what a page of another site may send without asking) is a 415; nothing is published."""
    headers = {"Content-Type": content_type} if content_type else {}
    r = client.post(f"{BASE}/{path}", content=body.encode(), headers=headers)
    assert r.status_code == 415 and "application/json" in r.json()["detail"]
    publisher.poll()
    assert not publisher.records


@pytest.mark.parametrize(
    "body, fragment",
    [
        (b"{not json", "meta.json"),
        (b'{"width": 4800}', "height"),
        (json.dumps({**META_8, "width": "wide"}).encode(), "width"),
        (json.dumps({**META_8, "CHUNK_ROWS": 3}).encode(), "do not cover"),
        (json.dumps({**META_8, "CHUNK_WIDTH": 0}).encode(), "CHUNK_WIDTH"),
    ],
)
def test_malformed_meta_is_400_and_publishes_nothing(client, publisher, body, fragment) -> None:
    """A meta.json that is not JSON, lacks a field, has a wrong type or an impossible grid is a 400."""
    r = client.post(f"{BASE}/meta", content=body, headers=JSON)
    assert r.status_code == 400 and fragment in r.json()["detail"]
    publisher.poll()
    assert not publisher.records


def test_writes_without_publisher_are_503(store, settings, wire) -> None:
    """With no event publisher configured, POST /meta and POST /chunks answer 503 saying why."""
    client = TestClient(create_app(settings, store, {}, ManualClock(CLOCK_MS)), headers=WRITER)
    for path, body in (("meta", META_8), ("chunks", wire.chunk_doc())):
        r = client.post(f"{BASE}/{path}", json=body)
        assert r.status_code == 503 and "publisher" in r.json()["detail"]


def test_kafka_failure_is_503(store, settings, wire) -> None:
    """When the event log refuses the record the write is a 503, not a silent success."""
    publisher = MemoryPublisher(fail_with=RuntimeError("broker down"))
    client = TestClient(create_app(settings, store, {}, ManualClock(CLOCK_MS), publisher=publisher))
    r = client.post(f"{BASE}/meta", json=META_8, headers=ADMIN)
    assert r.status_code == 503 and "broker down" in r.json()["detail"]


# --- POST /chunks (listings 10, 11) ------------------------------------------------------------


def test_post_chunk_is_the_same_event_as_mqtt(client, publisher, settings, wire) -> None:
    """Listing 10 via REST yields the very event an MQTT iot/chunks/create would, on the chunk topic."""
    wire.now_ms = CLOCK_MS
    doc = wire.chunk_doc(row=3, column=2, timestamp="2026-11-21T10:00:30")
    r = client.post(f"{BASE}/chunks", json=doc)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["_id"] == "row:3_column:2_2026-11-21T10:00:30"
    assert (body["_index"], body["_type"], body["result"], body["_version"]) == (
        "chunks",
        "chunk",
        "created",
        1,
    )
    assert isinstance(body["_shards"]["successful"], int)
    publisher.poll()
    [(key, value)] = publisher.records[settings.topic_chunk_events]
    via_mqtt = Router(settings, "gw").route(
        "iot/chunks/create",
        wire.chunk(row=3, column=2, timestamp="2026-11-21T10:00:30"),
        CLOCK_MS,
        Intake().with_meta(MapMetaSet(500, 400, 100, 100, 4, 5)),
    )
    assert key == via_mqtt.key == b"3:2"
    assert decode(value) == via_mqtt.envelope
    assert isinstance(decode(value).payload, ChunkUpdated)


@pytest.mark.parametrize(
    "overrides, reason",
    [
        ({"pgmB64compressedData": "not base64!"}, "bad_base64"),
        ({"row": 4}, "out_of_map"),  # the stored meta has 4 rows
        ({"timestamp": "2026-11-21T11:00:00"}, "timestamp_in_future"),
        ({"timestamp": "yesterday"}, "bad_timestamp"),
        ({"robotId": "bad id"}, "bad_robot_id"),
        (
            {"pgmB64compressedData": base64.b64encode(zlib.compress(bytes(99))).decode()},
            "wrong_chunk_size",
        ),
    ],
)
def test_post_chunk_is_validated_like_mqtt(client, publisher, wire, overrides, reason) -> None:
    """A chunk MQTT would dead-letter is a 400 naming the same reason; nothing is published."""
    wire.now_ms = CLOCK_MS
    r = client.post(f"{BASE}/chunks", json=wire.chunk_doc(**overrides))
    assert r.status_code == 400 and r.json()["detail"].startswith(reason), r.text
    publisher.poll()
    assert not publisher.records


def test_chunks_right_after_meta_use_the_posted_grid(client, store, publisher, wire) -> None:
    """Chunks POSTed right after POST /meta (not stored yet) are checked against its grid."""
    wire.now_ms = CLOCK_MS
    meta = {**META_8, "CHUNK_WIDTH": 50, "CHUNK_HEIGHT": 50, "CHUNK_ROWS": 64, "CHUNK_COLS": 96}
    assert client.post(f"{BASE}/meta", json=meta, headers=ADMIN).status_code == 200
    small = wire.chunk_doc(row=60, pgmB64compressedData=wire.b64z(bytes(2500)))
    r = client.post(f"{BASE}/chunks", json=small)
    assert r.status_code == 200, r.text
    process(publisher, store)
    assert (
        client.post(f"{BASE}/chunks", json=wire.chunk_doc())
        .json()["detail"]
        .startswith("wrong_chunk_size")
    )


@pytest.mark.parametrize("path", ["chunks", "meta"])
def test_oversized_body_is_413(client, publisher, settings, path) -> None:
    """A body over MAPSERVICE_MAX_MESSAGE_BYTES is refused (413) and nothing is published."""
    r = client.post(f"{BASE}/{path}", content=b" " * (settings.max_message_bytes + 1), headers=JSON)
    assert r.status_code == 413 and "oversized" in r.json()["detail"]
    publisher.poll()
    assert not publisher.records


def test_post_chunk_not_json_or_missing_field_is_400(client) -> None:
    """A body that is not JSON, or lacks a listing-10 field, is a 400."""
    assert (
        client.post(f"{BASE}/chunks", content=b"{", headers=JSON)
        .json()["detail"]
        .startswith("not_json")
    )
    r = client.post(f"{BASE}/chunks", json={"row": 1})
    assert r.status_code == 400 and r.json()["detail"].startswith("missing_field")


def test_read_your_own_write_by_id(client, store, publisher, wire) -> None:
    """Once the processors stored a POSTed chunk, GET /chunks/id/<_id> returns it (listing 13)."""
    wire.now_ms = CLOCK_MS
    doc = wire.chunk_doc(row=2, column=4, timestamp="2026-11-21T10:00:30.250", robotId="lkjlkj")
    chunk_id = client.post(f"{BASE}/chunks", json=doc).json()["_id"]
    assert chunk_id == "row:2_column:4_2026-11-21T10:00:30.250"
    assert client.get(f"{BASE}/chunks/id/{chunk_id}").status_code == 404
    assert process(publisher, store) == 1
    r = client.get(f"{BASE}/chunks/id/{chunk_id}")
    assert r.status_code == 200
    assert r.json() == {
        "row": 2,
        "column": 4,
        "timestamp": "2026-11-21T10:00:30.250",
        "chunk": doc["pgmB64compressedData"],
        "type": "pgm_base64_compressed",
        "id": chunk_id,
        "robotId": "lkjlkj",
    }
