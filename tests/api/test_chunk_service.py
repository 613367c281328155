"""The 2019 chunk service (appendix A.1) over a MemoryStore and an in-memory event log."""

from __future__ import annotations

import base64
import io
import json
import zlib

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mapservice.api.app import create_app
from mapservice.ingest.router import Router
from PIL import Image
from structlog.testing import capture_logs

from mapservice.adapters.clock import ManualClock
from mapservice.core.events import ChunkUpdated, MapMetaSet, decode
from mapservice.core.legacy_query import MAX_LIMIT
from mapservice.core.wire2019 import Limits
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from tests.fixtures.legacy import SpyStore, process

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
CLOCK_MS = NOW + 60_000
TOKEN = "test-admin-token"
ADMIN = {"Authorization": f"Bearer {TOKEN}"}
WRITER_TOKEN = "test-writer-token"  # a 2019 robot's: the header is all it adds
WRITER = {"Authorization": f"Bearer {WRITER_TOKEN}"}
JSON = {"Content-Type": "application/json"}
BASE = "/api/chunk-service"


def pixels(i: int) -> bytes:
    return bytes([i]) * 10_000


# (robot, offset ms, row, column) per write; writes 12 and 13 overwrite cell (0, 0) at one
# instant, and r2 > r1 wins it.
WRITES = [(f"r{i % 3}", i * 1000, i % 4, i % 5) for i in range(12)] + [
    ("r1", 12_000, 0, 0),
    ("r2", 12_000, 0, 0),
]


@pytest.fixture
def store(ev) -> SpyStore:
    s = SpyStore()
    s.append([ev.meta(NOW - 10_000, chunk_rows=4, chunk_cols=5)])
    s.append(
        [
            ev.chunk(robot, NOW + dt, row, col, pixels(i))
            for i, (robot, dt, row, col) in enumerate(WRITES)
        ]
    )
    return s


@pytest.fixture
def publisher() -> MemoryPublisher:
    return MemoryPublisher()


@pytest.fixture
def settings() -> Settings:
    return Settings(admin_token=TOKEN, api_writer_tokens=WRITER_TOKEN)


@pytest.fixture
def client(store, publisher, settings) -> TestClient:
    app = create_app(settings, store, {}, ManualClock(CLOCK_MS), publisher=publisher)
    return TestClient(app, raise_server_exceptions=False, headers=WRITER)


def anonymous(client: TestClient) -> TestClient:
    """The same app, asked without a credential."""
    return TestClient(client.app, raise_server_exceptions=False)


def get(client, **params):
    r = client.get(f"{BASE}/chunks", params=params)
    assert r.status_code == 200, r.text
    return r.json()


def keys(body) -> list[tuple]:
    """(robot, offset ms, row, column) of each returned chunk, in order."""
    return [(c["robotId"], _ms(c["timestamp"]) - NOW, c["row"], c["column"]) for c in body]


def _ms(ts: str) -> int:
    from mapservice.core.wire2019 import parse_timestamp

    return parse_timestamp(ts)


def newest_first(writes):
    return sorted(writes, key=lambda w: (-w[1], w[2], w[3], w[0]))


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
        Limits().with_meta(MapMetaSet(500, 400, 100, 100, 4, 5)),
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


# --- GET /chunks (listing 12): every parameter --------------------------------------------------


def test_listing_12_fields_and_types(client) -> None:
    """Each chunk has row, column, timestamp, chunk (base64 zlib pixels), type, id and robotId."""
    [first] = get(client, limit=1)
    assert first == {
        "row": 0,
        "column": 0,
        "timestamp": "2026-11-21T10:00:12",
        "chunk": first["chunk"],
        "type": "pgm_base64_compressed",
        "id": "row:0_column:0_2026-11-21T10:00:12",
        "robotId": "r1",
    }
    assert zlib.decompress(base64.b64decode(first["chunk"])) == pixels(12)


def test_defaults_are_ten_newest_first(client) -> None:
    """No parameters: limit 10, sorted timestamp:desc (ties by row, column, robot)."""
    assert keys(get(client)) == newest_first(WRITES)[:10]


def test_limit_and_skip(client) -> None:
    """limit cuts, skip pages on from there."""
    assert keys(get(client, limit=3)) == newest_first(WRITES)[:3]
    assert keys(get(client, limit=3, skip=2)) == newest_first(WRITES)[2:5]
    assert keys(get(client, limit=MAX_LIMIT)) == newest_first(WRITES)


@pytest.mark.parametrize(
    "param, value, expected",
    [
        ("row", "1", lambda w: w[2] == 1),
        ("column", "0", lambda w: w[3] == 0),
        ("robotId", "r1", lambda w: w[0] == "r1"),
        ("timestamp", "2026-11-21T10:00:12", lambda w: w[1] == 12_000),
        ("timestamp", str(NOW + 12_000), lambda w: w[1] == 12_000),
        ("updatedSince", "2026-11-21T10:00:11", lambda w: w[1] >= 11_000),
        ("updatedBefore", "2026-11-21T10:00:02Z", lambda w: w[1] < 2_000),
        ("updatedBefore", "2026-11-21T11:00:02+01:00", lambda w: w[1] < 2_000),
    ],
)
def test_filters(client, param, value, expected) -> None:
    """Each filter selects exactly its writes (since inclusive, before exclusive, no zone = UTC)."""
    assert keys(get(client, limit=100, **{param: value})) == newest_first(
        [w for w in WRITES if expected(w)]
    )


@pytest.mark.parametrize(
    "sort, order",
    [
        ("timestamp:asc", lambda w: (w[1], w[2], w[3], w[0])),
        ("timestamp:desc", lambda w: (-w[1], w[2], w[3], w[0])),
        ("row:asc", lambda w: (w[2], -w[1], w[3], w[0])),
        ("column:desc,robotId:asc", lambda w: (-w[3], w[0], -w[1], w[2])),
    ],
)
def test_sort(client, sort, order) -> None:
    """sort orders by the whitelisted fields, the identity breaking ties."""
    assert keys(get(client, limit=100, sort=sort)) == sorted(WRITES, key=order)


def test_latest_is_each_cells_winner(client, store) -> None:
    """latest=true: one write per chunk, the newest; at one instant the greatest robot id."""
    body = keys(get(client, latest="true", limit=100))
    assert len(body) == 12
    assert ("r2", 12_000, 0, 0) in body and ("r1", 12_000, 0, 0) not in body
    assert ("r0", 0, 0, 0) not in body
    assert store.called("map_at") == [CLOCK_MS + 300_000]  # now plus the allowed clock skew


def test_latest_with_updated_before_is_the_map_at_t_from_map_at(client, store) -> None:
    """latest=true&updatedBefore=T is the whole map just before T, served by map_at (no scan)."""
    body = keys(get(client, latest="true", updatedBefore="2026-11-21T10:00:05", limit=100))
    assert body == newest_first(WRITES[:5])
    assert store.called("map_at") == [NOW + 4_999]
    assert store.called("list_chunks") == []


def test_latest_then_filters_select_among_winners(client) -> None:
    """With latest, row/robotId filter the winners (cell (0,0) is r2's now, so r0 has none there)."""
    assert keys(get(client, latest="true", row="0", robotId="r0", limit=100)) == []
    assert keys(get(client, latest="true", row="0", limit=100)) == newest_first(
        [w for w in WRITES if w[2] == 0 and w[1] != 0 and w[:2] != ("r1", 12_000)]
    )


def test_reduced_leaves_out_chunk_and_type(client) -> None:
    """reduced=true omits `chunk` and `type`; the rest stays."""
    [c] = get(client, limit=1, reduced="true")
    assert set(c) == {"row", "column", "timestamp", "id", "robotId"}
    assert set(get(client, limit=1, reduced="false")[0]) >= {"chunk", "type"}


def test_type_png_returns_base64_png(client) -> None:
    """type=png puts a base64 PNG of the chunk's pixels in `chunk`."""
    [c] = get(client, limit=1, type="png")
    assert c["type"] == "png"
    image = np.asarray(Image.open(io.BytesIO(base64.b64decode(c["chunk"]))))
    assert image.shape == (100, 100) and image.tobytes() == pixels(12)


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"row": "abc"}, "'row'"),
        ({"column": "-1"}, "'column'"),
        ({"limit": str(MAX_LIMIT + 1)}, "'limit'"),
        ({"limit": "ten"}, "'limit'"),
        ({"skip": "9995", "limit": "10"}, "skip + limit"),
        ({"sort": "timestamp; DROP TABLE chunk_events"}, "'sort'"),
        ({"sort": "chunk:asc"}, "'sort'"),
        ({"sort": "row:sideways"}, "'sort'"),
        ({"latest": "maybe"}, "'latest'"),
        ({"reduced": "yes please"}, "'reduced'"),
        ({"type": "gif"}, "'type'"),
        ({"timestamp": "yesterday"}, "'timestamp'"),
        ({"updatedSince": "2026-13-01"}, "'updatedSince'"),
        ({"updatedBefore": "soon"}, "'updatedBefore'"),
    ],
)
def test_malformed_parameters_are_400(client, params, fragment) -> None:
    """A malformed value is a 400 naming the parameter and what it accepts."""
    r = client.get(f"{BASE}/chunks", params=params)
    assert r.status_code == 400 and fragment in r.json()["detail"], r.text


def test_unknown_parameters_are_ignored(client) -> None:
    """Parameters the 2019 document does not know are ignored, as the 2019 service did."""
    assert get(client, foo="bar", limit=2, page="7") == get(client, limit=2)


# --- GET /chunks/id/{id} and /png ---------------------------------------------------------------


def test_get_by_id_picks_the_winner_of_a_shared_instant(client) -> None:
    """An id names (row, column, time); two robots at that instant: the greatest robot id."""
    r = client.get(f"{BASE}/chunks/id/row:0_column:0_2026-11-21T10:00:12")
    assert r.status_code == 200 and r.json()["robotId"] == "r2"
    assert zlib.decompress(base64.b64decode(r.json()["chunk"])) == pixels(13)


@pytest.mark.parametrize(
    "chunk_id",
    ["row:0_column:0_2026-11-21T10:00:13", "nonsense", "row:x_column:0_2026-11-21T10:00:12"],
)
def test_unknown_or_malformed_id_is_404(client, chunk_id) -> None:
    """An id that names no stored chunk (or no chunk at all) is a 404 with a message."""
    for suffix in ("", "/png"):
        r = client.get(f"{BASE}/chunks/id/{chunk_id}{suffix}")
        assert r.status_code == 404 and "no chunk" in r.json()["detail"]


def test_png_by_id(client) -> None:
    """/chunks/id/{id}/png is the chunk as a greyscale PNG."""
    r = client.get(f"{BASE}/chunks/id/row:2_column:2_2026-11-21T10:00:02/png")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert np.asarray(Image.open(io.BytesIO(r.content))).tobytes() == pixels(2)


# --- DELETE (administrative) ------------------------------------------------------------------


@pytest.mark.parametrize("path", ["chunks", "meta"])
def test_delete_needs_the_admin_token(client, store, path) -> None:
    """DELETE without a token or with a wrong one is 401, with a robot's (writer) token 403; nothing is deleted."""
    assert anonymous(client).delete(f"{BASE}/{path}").status_code == 401
    r = client.delete(f"{BASE}/{path}", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401
    r = client.delete(f"{BASE}/{path}")
    assert r.status_code == 403 and "MAPSERVICE_ADMIN_TOKEN" in r.json()["detail"]
    assert store.counts().chunk_events == len(WRITES) and store.latest_meta() is not None


def test_delete_chunks_with_token_empties_and_logs(client, store) -> None:
    """DELETE /chunks with the admin token removes every chunk write and logs who did it."""
    with capture_logs() as logs:
        r = client.delete(f"{BASE}/chunks", headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200 and r.json() == {"acknowledged": True, "deleted": len(WRITES)}
    assert get(client) == [] and get(client, latest="true") == []
    assert any(e["event"] == "chunk history deleted by administrator" for e in logs)


def test_delete_meta_with_token(client, store) -> None:
    """DELETE /meta with the admin token removes the meta: GET /meta is then a 404."""
    r = client.delete(f"{BASE}/meta", headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200 and r.json()["deleted"] == 1
    assert client.get(f"{BASE}/meta").status_code == 404
