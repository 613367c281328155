"""The HTTP API over a MemoryStore: health, history windows, chunk contents, stats, ids."""

from __future__ import annotations

import zlib

import pytest
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.api.routers.chunk_contents import IMMUTABLE
from mapservice.core.wire2019 import content_hash
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.api.test_webhooks import WEBHOOK_OPERATION_IDS

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
HOUR = 3_600_000
PIXELS = bytes(i % 256 for i in range(100 * 100))
HASH = content_hash(PIXELS).hex()

EXPECTED_OPERATION_IDS = {
    "getLiveness",
    "getReadiness",
    "listPoses",
    "listChunkEvents",
    "getChunkContent",
    "getHistoryStats",
    "getMapAt",
    "getRobotsAt",
    "getMapPngAt",
    # the 2019 REST contract (api/routers/chunk_service.py, coordinate_service.py)
    "getLegacyMeta",
    "postLegacyMeta",
    "putLegacyMeta",
    "deleteLegacyMeta",
    "postLegacyChunk",
    "listLegacyChunks",
    "deleteLegacyChunks",
    "getLegacyChunk",
    "getLegacyChunkPng",
    "listLegacyRobots",
    # time-travel replay reads (api/routers/events.py, timeline.py, tracks.py)
    "listEvents",
    "getTimeline",
    "getRobotTrack",
    "getRobotTrackBuckets",
    "listConflicts",
    "getChunkContentsBatch",  # api/routers/chunk_contents.py (replay UI seeks)
    "getClientConfig",  # api/routers/client_config.py (the /controller page)
    "getServiceStatus",  # api/routers/status.py (the replay UI's "history not stored" banner)
    "exportTable",
    "exportReplayMcap",  # api/routers/exports.py
    "listChanges",  # api/routers/changes.py (the replay UI's change feed)
    "getVdaVehicle",  # api/routers/vda5050.py (a VDA 5050 vehicle's errors, connection, factsheet)
    "getVdaFleet",  # api/routers/vda5050.py (every VDA 5050 vehicle's facts of a window)
    # operators' annotations (api/routers/annotations.py, costmap_filters.py, zone_violations.py)
    "listAnnotations",
    "listAnnotationEdits",
    "createAnnotation",
    "changeAnnotation",
    "removeAnnotation",
    "importKeepOutMask",
    "getCostmapFilterMask",
    "getCostmapFilterMaskYaml",
    "getCostmapFilterInfo",
    "listZoneViolations",
    "listIncidents",
    "getHeatmap",
    "sendCommand",
    "listCommands",  # api/routers/commands.py (operators' commands to robots)
    "getCallerAccess",  # api/routers/caller.py (the replay page offers editing to operators)
} | WEBHOOK_OPERATION_IDS


@pytest.fixture
def store(ev) -> MemoryStore:
    s = MemoryStore()
    s.append(
        [
            ev.pose("r1", NOW, x=1.0, y=2.0, charging=True, loaded="dfs"),
            ev.pose("r2", NOW, x=5.0, y=6.0, path=((1.0, 1.0), (2.0, 2.0))),
            ev.pose("r1", NOW + 1000, x=1.5, y=2.0),
            ev.pose("r1", NOW + 2000, x=2.0, y=2.0),
            ev.chunk("r1", NOW + 500, 3, 2, PIXELS),
            ev.chunk("r2", NOW + 1500, 0, 1, PIXELS),
            ev.chunk("r2", NOW + 2500, 0, 1, bytes(10_000)),
        ]
    )
    s.append_dead_letters([ev.dead_letter()])
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(NOW + 60_000)), raise_server_exceptions=False
    )


def _window(path: str, client: TestClient, f, t, **params):
    return client.get(path, params={"from": f, "to": t, **params})


# --- health ------------------------------------------------------------------------------


def test_healthz(client) -> None:
    """/healthz answers 200 {"ok": true}."""
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"ok": True}


def test_readyz_without_checks_is_ready(client) -> None:
    """/readyz with no checks is ready (200)."""
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json() == {"ok": True, "checks": {}}


def test_readyz_reports_failing_check(store) -> None:
    """/readyz is 503 and names the failing check when one is not ready."""
    app = create_app(Settings(), store, {"store": lambda: True, "kafka": lambda: False})
    r = TestClient(app).get("/readyz")
    assert r.status_code == 503
    assert r.json() == {"ok": False, "checks": {"store": True, "kafka": False}}


def test_metrics_are_prometheus_text(client) -> None:
    """/metrics serves the Prometheus exposition format."""
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")


def test_metrics_count_requests_per_route_template_and_status(client) -> None:
    """Requests are counted per route template and status (not per URL); probes and scrapes are not counted."""
    from prometheus_client import REGISTRY

    def count(path: str, status: str) -> float:
        return (
            REGISTRY.get_sample_value(
                "mapservice_api_requests_total",
                {
                    "app_name": "mapservice-api",
                    "method": "GET",
                    "path": path,
                    "status_code": status,
                },
            )
            or 0.0
        )

    template = "/api/v1/chunk-contents/{content_hash}"
    before_ok, before_404 = count(template, "200"), count(template, "404")
    healthz_before = count("/healthz", "200")
    client.get("/api/v1/chunk-contents/" + "00" * 16)
    client.get("/api/v1/chunk-contents/" + "11" * 16)
    client.get("/healthz")
    assert count(template, "404") == before_404 + 2 and count(template, "200") == before_ok
    assert count("/healthz", "200") == healthz_before == 0
    text = client.get("/metrics").text
    assert "mapservice_api_request_duration_seconds_bucket" in text


# --- poses ---------------------------------------------------------------------------------


def test_poses_window_iso(client) -> None:
    """ISO from/to select [from, to), ordered by time then robot, with 2019-style timestamps."""
    r = _window("/api/v1/poses", client, "2026-11-21T10:00:00Z", "2026-11-21T10:00:02Z")
    assert r.status_code == 200, r.text
    body = r.json()
    assert [(p["robotId"], p["ts_ms"]) for p in body] == [
        ("r1", NOW),
        ("r2", NOW),
        ("r1", NOW + 1000),
    ]
    first = body[0]
    assert first["timestamp"] == "2026-11-21T10:00:00"
    assert first["position"] == [1.0, 2.0, 0.0]
    assert first["orientation"] == [0.0, 0.0, 0.0, 1.0]
    assert first["charging"] is True and first["loaded"] == "dfs"
    assert first["receive_time_ms"] == NOW + 40
    assert body[1]["path"] == [[1.0, 1.0], [2.0, 2.0]] and first["path"] is None


def test_poses_window_epoch_ms_and_zoneless_iso_agree(client) -> None:
    """Epoch milliseconds and zoneless ISO (UTC) select the same window."""
    a = _window("/api/v1/poses", client, NOW + 1, NOW + 2001).json()
    b = _window(
        "/api/v1/poses", client, "2026-11-21T10:00:00.001", "2026-11-21T10:00:02.001"
    ).json()
    assert a == b
    assert [p["ts_ms"] for p in a] == [NOW + 1000, NOW + 2000]


def test_poses_robot_filter_and_limit(client) -> None:
    """robotId filters to one robot; limit cuts the earliest rows."""
    r = _window("/api/v1/poses", client, NOW, NOW + HOUR, robotId="r1", limit=2)
    assert [(p["robotId"], p["ts_ms"]) for p in r.json()] == [("r1", NOW), ("r1", NOW + 1000)]


def test_empty_window_is_an_empty_list(client) -> None:
    """A window with no poses answers 200 []."""
    r = _window("/api/v1/poses", client, NOW - HOUR, NOW)
    assert r.status_code == 200 and r.json() == []


# --- chunk events -------------------------------------------------------------------------


def test_chunk_events_window(client) -> None:
    """Chunk events in [from, to) in event-time order, with the content hash to fetch."""
    r = _window("/api/v1/chunk-events", client, NOW + 500, NOW + 2500)
    assert r.status_code == 200, r.text
    body = r.json()
    assert [(c["row"], c["column"], c["robotId"], c["ts_ms"]) for c in body] == [
        (3, 2, "r1", NOW + 500),
        (0, 1, "r2", NOW + 1500),
    ]
    assert body[0]["content_hash"] == HASH
    assert body[0]["timestamp"] == "2026-11-21T10:00:00.500"
    assert body[0]["receive_time_ms"] == NOW + 525


# --- bad windows ------------------------------------------------------------------------

WINDOW_PATHS = ["/api/v1/poses", "/api/v1/chunk-events"]


@pytest.mark.parametrize("path", WINDOW_PATHS)
@pytest.mark.parametrize("bad", ["yesterday", "2026-11-21T25:00:00", "--5", "1-2", "²", "12ab"])
def test_bad_time_is_400_with_a_helpful_message(client, path, bad) -> None:
    """An unparseable time is a 400 naming the parameter and the accepted formats."""
    r = _window(path, client, bad, NOW)
    assert r.status_code == 400, r.text
    detail = r.json()["detail"]
    assert "'from'" in detail and "ISO 8601" in detail and "epoch milliseconds" in detail
    r = _window(path, client, NOW, bad)
    assert r.status_code == 400 and "'to'" in r.json()["detail"]


@pytest.mark.parametrize("path", WINDOW_PATHS)
def test_from_after_to_is_400(client, path) -> None:
    """from > to is a 400 that says to swap them."""
    r = _window(path, client, NOW + 1000, NOW)
    assert r.status_code == 400
    assert "swap" in r.json()["detail"]


@pytest.mark.parametrize("path", WINDOW_PATHS)
def test_too_long_window_is_400(client, path) -> None:
    """A window longer than 24 h is a 400 that says to split it; exactly 24 h is fine."""
    r = _window(path, client, NOW, NOW + 24 * HOUR + 1)
    assert r.status_code == 400
    assert "longer than" in r.json()["detail"] and "split" in r.json()["detail"]
    assert _window(path, client, NOW, NOW + 24 * HOUR).status_code == 200
    assert _window(path, client, "2026-11-20T10:00:00Z", "2026-11-21T10:00:00Z").status_code == 200


@pytest.mark.parametrize("path", WINDOW_PATHS)
def test_missing_window_is_422(client, path) -> None:
    """from and to are required."""
    assert client.get(path, params={"from": NOW}).status_code == 422


# --- chunk contents -----------------------------------------------------------------------


def test_chunk_content_bytes_and_immutable_cache(client, store) -> None:
    """A known hash returns the zlib bytes as sent, cacheable forever, with size headers."""
    r = client.get(f"/api/v1/chunk-contents/{HASH}")
    assert r.status_code == 200
    assert r.content == store.chunk_content(bytes.fromhex(HASH))[2]
    assert zlib.decompress(r.content) == PIXELS
    assert r.headers["content-type"] == "application/octet-stream"
    assert r.headers["cache-control"] == IMMUTABLE == "public, max-age=31536000, immutable"
    assert r.headers["etag"] == f'"{HASH}"'
    assert (r.headers["x-chunk-width"], r.headers["x-chunk-height"]) == ("100", "100")


def test_chunk_content_raw_encoding(client) -> None:
    """encoding=raw returns the width x height pixels."""
    r = client.get(f"/api/v1/chunk-contents/{HASH}", params={"encoding": "raw"})
    assert r.status_code == 200 and r.content == PIXELS
    assert (
        client.get(f"/api/v1/chunk-contents/{HASH}", params={"encoding": "bmp"}).status_code == 422
    )


def test_unknown_chunk_content_is_404(client) -> None:
    """A well-formed hash that is not stored is a 404."""
    r = client.get(f"/api/v1/chunk-contents/{'0' * 32}")
    assert r.status_code == 404 and "0" * 32 in r.json()["detail"]


@pytest.mark.parametrize("bad", ["abc", HASH.upper(), HASH[:-1], HASH + "0", "g" * 32])
def test_malformed_hash_is_400(client, bad) -> None:
    """A hash that is not 32 lowercase hex characters is a 400."""
    r = client.get(f"/api/v1/chunk-contents/{bad}")
    assert r.status_code == 400 and "32 lowercase hex" in r.json()["detail"]


# --- stats and ids ------------------------------------------------------------------------


def test_stats_counts(client) -> None:
    """/api/v1/stats reports the store's counts."""
    r = client.get("/api/v1/stats")
    assert r.status_code == 200
    assert r.json() == {"poses": 4, "chunk_events": 3, "chunk_contents": 2, "dead_letters": 1}


def _api_routes(routes):
    """APIRoutes, looking inside included routers (FastAPI >= 0.12x keeps them nested)."""
    for route in routes:
        if isinstance(route, APIRoute):
            yield route
        elif hasattr(route, "original_router"):
            yield from _api_routes(route.original_router.routes)


# The documentation pages fastapi-offline adds (not API operations, not in the schema).
DOC_PAGES = {"/docs", "/docs/oauth2-redirect", "/redoc"}


def test_every_route_has_an_operation_id(client) -> None:
    """Every API route declares an explicit, unique operation id."""
    routes = [r for r in _api_routes(client.app.routes) if r.path not in DOC_PAGES]
    assert {r.path for r in routes} >= {
        "/healthz",
        "/readyz",
        "/metrics",
        "/api/v1/poses",
        "/api/v1/chunk-events",
        "/api/v1/stats",
        "/api/v1/chunk-contents/{content_hash}",
    }
    ids = [r.operation_id for r in routes]
    assert all(ids), [r.path for r in routes if not r.operation_id]
    assert len(ids) == len(set(ids))


def test_openapi_lists_the_stable_operation_ids(client) -> None:
    """The OpenAPI document lists exactly the stable operationIds that clients are generated from."""
    doc = client.get("/openapi.json").json()
    ids = [op["operationId"] for item in doc["paths"].values() for op in item.values()]
    assert sorted(ids) == sorted(EXPECTED_OPERATION_IDS)


# --- time travel -------------------------------------------------------------------------


def test_map_at_returns_each_chunks_winning_write(client) -> None:
    """/api/v1/map?at=T lists, per chunk, the newest write at or before T."""
    body = client.get("/api/v1/map", params={"at": NOW + 2000}).json()
    chunks = {(c["row"], c["column"]): c for c in body["chunks"]}
    assert set(chunks) == {(3, 2), (0, 1)}
    assert chunks[(0, 1)]["ts_ms"] == NOW + 1500 and chunks[(0, 1)]["robotId"] == "r2"
    later = client.get("/api/v1/map", params={"at": NOW + 3000}).json()
    assert {(c["row"], c["column"]): c["ts_ms"] for c in later["chunks"]}[(0, 1)] == NOW + 2500


def test_robots_at_returns_latest_pose_with_age(client) -> None:
    """/api/v1/robots?at=T gives each robot's latest pose at or before T and its age."""
    body = client.get("/api/v1/robots", params={"at": NOW + 1500}).json()
    robots = {r["robotId"]: r for r in body["robots"]}
    assert robots["r1"]["ts_ms"] == NOW + 1000 and robots["r1"]["age_ms"] == 500
    assert robots["r1"]["position"][0] == 1.5
    assert robots["r2"]["path"] == [[1.0, 1.0], [2.0, 2.0]]


@pytest.mark.parametrize(
    "at, fragment",
    [
        (str(NOW + 3_600_000), "future"),
        (str(NOW - 8 * 86_400_000), "retention"),
        ("yesterday", "ISO 8601"),
    ],
)
def test_instant_outside_retention_or_malformed_is_400(client, at, fragment) -> None:
    """An instant in the future, beyond the retention or malformed gets a 400 saying why."""
    for path in ("/api/v1/map", "/api/v1/robots"):
        r = client.get(path, params={"at": at})
        assert r.status_code == 400 and fragment in r.json()["detail"]


# --- pictures ----------------------------------------------------------------------------


def _png_pixels(body: bytes):
    import io

    import numpy as np
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(body)))


def test_map_png_at_t_has_each_chunks_pixels_in_place(store, ev) -> None:
    """/api/v1/map/png?at=T stitches the winning chunks at their row/column; unwritten is 205."""
    store.append([ev.meta(NOW - 1000, chunk_rows=4, chunk_cols=5)])
    client = TestClient(create_app(Settings(), store, {}, ManualClock(NOW + 60_000)))
    r = client.get("/api/v1/map/png", params={"at": NOW + 2000})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = _png_pixels(r.content)
    assert img.shape == (400, 500)
    assert img[300:400, 200:300].tobytes() == PIXELS  # row 3, column 2
    assert img[0:100, 100:200].tobytes() == PIXELS  # row 0, column 1 at NOW + 1500
    assert (img[100:200, 0:100] == 205).all()
    later = _png_pixels(client.get("/api/v1/map/png", params={"at": NOW + 3000}).content)
    assert (later[0:100, 100:200] == 0).all()  # replaced at NOW + 2500 by zeros
    half = _png_pixels(
        client.get("/api/v1/map/png", params={"at": NOW + 3000, "scale": 0.5}).content
    )
    assert half.shape == (200, 250)


def test_map_png_without_meta_is_404(client) -> None:
    """Without a map meta there is no geometry to stitch: 404 with a hint."""
    r = client.get("/api/v1/map/png")
    assert r.status_code == 404 and "meta" in r.json()["detail"]


def test_chunk_content_as_png(client) -> None:
    """encoding=png returns the chunk as a 100 x 100 greyscale PNG, immutable."""
    from mapservice.core.wire2019 import content_hash

    r = client.get(
        f"/api/v1/chunk-contents/{content_hash(PIXELS).hex()}", params={"encoding": "png"}
    )
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert "immutable" in r.headers["cache-control"]
    assert _png_pixels(r.content).tobytes() == PIXELS


def test_api_docs_need_no_internet(client) -> None:
    """/docs and /redoc load Swagger UI and ReDoc from this server (no external host), and those files answer."""
    import re

    for page in ("/docs", "/redoc"):
        r = client.get(page)
        assert r.status_code == 200
        urls = re.findall(r'(?:src|href)="([^"]+)"|url: *[\'"]([^\'"]+)[\'"]', r.text)
        assets = [u for pair in urls for u in pair if u]
        assert assets, page
        assert not [u for u in assets if re.match(r"https?://", u)], assets
        for asset in assets:
            assert client.get(asset).status_code == 200, asset


def test_poses_and_chunk_events_json_equals_their_pydantic_models() -> None:
    """The msgspec-encoded rows of /api/v1/poses and /api/v1/chunk-events decode to what
    the documented models (Pose, ChunkEvent) validate and dump, field for field and in order."""
    import json

    from fastapi.testclient import TestClient

    from mapservice.api.app import create_app
    from mapservice.api.routers.chunk_events import ChunkEvent
    from mapservice.api.routers.poses import Pose
    from mapservice.core.events import ChunkUpdated, PoseReported, make_envelope
    from mapservice.settings import Settings
    from mapservice.testing.memory_store import MemoryStore

    store = MemoryStore()
    store.append(
        [
            make_envelope(
                "r1",
                1_000,
                1_005,
                PoseReported(
                    (1.0, 2.5, 0.0),
                    (0.0, 0.0, 0.5, 0.8660254),
                    55.5,
                    "yes",
                    True,
                    ((1.0, 2.0), (3.0, 4.5)),
                ),
            ),
            make_envelope(
                "r2",
                2_001,
                2_010,
                PoseReported((-3.25, 1e-7, 0.0), (0.0, 0.0, 0.0, 1.0), None, None, None, None),
            ),
            make_envelope("r1", 3_000, 3_002, ChunkUpdated(2, 3, 100, 100, b"x", bytes(range(16)))),
        ]
    )
    client = TestClient(create_app(Settings(), store, {}))
    poses = client.get("/api/v1/poses", params={"from": 0, "to": 10_000}).json()
    chunks = client.get("/api/v1/chunk-events", params={"from": 0, "to": 10_000}).json()
    assert [json.loads(Pose(**p).model_dump_json()) for p in poses] == poses and len(poses) == 2
    assert [list(p) for p in poses] == [list(Pose.model_fields)] * 2
    assert [json.loads(ChunkEvent(**c).model_dump_json()) for c in chunks] == chunks and len(
        chunks
    ) == 1
    assert list(chunks[0]) == list(ChunkEvent.model_fields)
