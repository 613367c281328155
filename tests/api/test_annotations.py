"""Operators' annotations through the API: who may edit, events on Kafka with who and when,
the annotations at any instant, validation that says why, and the zones as nav2 costmap
filter masks (pixel for pixel against an independent rasterisation; the warehouse's own
keep-out mask imported and exported unchanged)."""

from __future__ import annotations

import base64
import io
import math
import random
from pathlib import Path

import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient
from PIL import Image

from mapservice.adapters.clock import ManualClock
from mapservice.adapters.ros_map import classify, load_ros_map, meta_for
from mapservice.api.app import create_app
from mapservice.api.context import context_of
from mapservice.core.annotations import AnnotationCreated, AnnotationRemoved
from mapservice.core.events import decode, make_envelope
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import meta_event

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
OPERATOR = "operator-" + "p" * 32
READER = "viewer-" + "r" * 32
WRITER = "writer-" + "w" * 32
ROBOT = "robot-" + "o" * 32
KEEPOUT_YAML = Path("/work/shared/maps/warehouse_keepout.yaml")


class World:
    """The API over a memory store, with the processors' part played by `store_published`."""

    def __init__(self, meta=None, **settings) -> None:
        self.settings = Settings(
            api_operator_tokens=OPERATOR,
            api_reader_tokens=READER,
            api_writer_tokens=WRITER,
            api_robot_tokens=f"agv-1={ROBOT}",
            api_rate_limit="",
            admin_token="admin-" + "a" * 32,
            **settings,
        )
        self.store = MemoryStore()
        self.store.append([meta or meta_event(NOW - 86_400_000)])
        self.clock = ManualClock(NOW)
        self.publisher = MemoryPublisher()
        self.client = TestClient(
            create_app(self.settings, self.store, {}, self.clock, publisher=self.publisher)
        )
        self._stored = 0

    def store_published(self) -> list:
        records = self.publisher.records[self.settings.topic_annotation_events]
        events = [decode(v) for _, v in records[self._stored :]]
        self._stored = len(records)
        self.store.append(events)
        return events

    def as_(self, token: str) -> dict:
        return {"Authorization": f"Bearer {token}"}

    def create(self, body: dict, token: str = OPERATOR):
        return self.client.post("/api/v1/annotations", json=body, headers=self.as_(token))

    def at(self, t: int) -> dict:
        r = self.client.get("/api/v1/annotations", params={"at": str(t)})
        assert r.status_code == 200, r.text
        return {a["id"]: a for a in r.json()["annotations"]}


def square(x0: float, y0: float, size: float) -> list[list[float]]:
    return [[x0, y0], [x0 + size, y0], [x0 + size, y0 + size], [x0, y0 + size]]


def keep_out(name: str, polygon, **extra) -> dict:
    return {"shape": "zone", "name": name, "kind": "keep_out", "polygon": polygon, **extra}


DOCK = {"shape": "poi", "name": "dock 1", "kind": "station", "x": 3.5, "y": 4.0, "heading": 1.57}


def test_readers_robots_and_writers_may_not_shape_the_floor_and_are_told_why() -> None:
    """Only an operator (or the admin) creates, changes or removes annotations; everyone
    else gets a 401/403 naming the operator scope, and nothing reaches Kafka."""
    w = World()
    for token, status in ((READER, 403), (ROBOT, 403), (WRITER, 403), (None, 401)):
        headers = w.as_(token) if token else {}
        for method, url in (
            ("POST", "/api/v1/annotations"),
            ("PUT", "/api/v1/annotations/x"),
            ("DELETE", "/api/v1/annotations/x"),
        ):
            r = w.client.request(
                method, url, json=DOCK if method != "DELETE" else None, headers=headers
            )
            assert r.status_code == status, (token, method, r.text)
            assert "operator" in r.json()["detail"]
    assert not w.publisher.records[w.settings.topic_annotation_events]
    assert w.create(DOCK).status_code == 201


def test_edits_are_events_with_who_and_when_and_the_annotations_travel_in_time() -> None:
    """Create, change, remove: each an event on the annotation topic (keyed by annotation,
    carrying the operator's credential name); the list at each instant shows the state then."""
    w = World()
    r = w.create({**DOCK, "id": "dock-1"})
    assert r.status_code == 201, r.text
    author = r.json()["created_by"]
    assert author.startswith("operator:") and OPERATOR not in author
    t_created = NOW
    events = w.store_published()  # the processors store each edit within seconds
    w.clock.advance(60_000)
    zone = keep_out("aisle 3", square(1.0, 1.0, 2.0))
    zone_id = w.create(zone).json()["id"]
    events += w.store_published()
    w.clock.advance(60_000)
    moved = {**DOCK, "x": 7.25, "name": "dock 1 (moved)"}
    r = w.client.put("/api/v1/annotations/dock-1", json=moved, headers=w.as_(OPERATOR))
    assert r.status_code == 200 and r.json()["created_ms"] == t_created, r.text
    events += w.store_published()
    w.clock.advance(60_000)
    assert (
        w.client.delete(f"/api/v1/annotations/{zone_id}", headers=w.as_(OPERATOR)).status_code
        == 204
    )
    events += w.store_published()
    assert [e.type for e in events] == [
        "annotation.created",
        "annotation.created",
        "annotation.changed",
        "annotation.removed",
    ]
    assert all(e.payload.author == author for e in events)
    keys = [k for k, _ in w.publisher.records[w.settings.topic_annotation_events]]
    assert keys[0] == b"annotation:dock-1"
    # Forget this process's own recent edits: what follows is the store's answer.
    context_of(w.client.app).recent_edits.edits = []
    assert w.at(NOW - 1) == {}
    assert list(w.at(NOW)) == ["dock-1"] and w.at(NOW)["dock-1"]["annotation"]["x"] == 3.5
    assert set(w.at(NOW + 60_000)) == {"dock-1", zone_id}
    after_move = w.at(NOW + 120_000)
    assert after_move["dock-1"]["annotation"]["name"] == "dock 1 (moved)"
    assert after_move["dock-1"]["changed_ms"] == NOW + 120_000
    assert set(w.at(NOW + 180_000)) == {"dock-1"}
    edits = w.client.get(
        "/api/v1/annotations/edits", params={"from": str(NOW - 1000), "to": str(NOW + 200_000)}
    ).json()["edits"]
    assert [(e["id"], e["change"]) for e in edits] == [
        ("dock-1", "created"),
        (zone_id, "created"),
        ("dock-1", "changed"),
        (zone_id, "removed"),
    ]
    # The removed zone is no longer in the keep-out mask from its removal on.
    assert _mask(w, "keepout", NOW + 60_000).min() == 0
    assert _mask(w, "keepout", NOW + 180_000).min() == 254


def test_an_operator_sees_their_edit_before_the_processors_stored_it() -> None:
    w = World()
    r = w.create({**DOCK, "id": "d"})
    assert r.status_code == 201
    assert "d" in w.at(NOW)  # not stored yet: this process's own edit
    assert w.client.delete("/api/v1/annotations/d", headers=w.as_(OPERATOR)).status_code == 204
    # The removal in the same millisecond is stamped a millisecond later: edits of one
    # annotation are ordered by their time.
    assert "d" in w.at(NOW) and "d" not in w.at(NOW + 1)


@pytest.mark.parametrize(
    "body, says",
    [
        (keep_out("bow tie", [[0, 0], [3, 3], [3, 0], [0, 1]]), "crosses itself"),
        (keep_out("line", [[0, 0], [1, 1]]), "at least 3"),
        (keep_out("flat", [[0, 0], [1, 1], [2, 2]]), "no area"),
        (keep_out("dup", [[0, 0], [1, 0], [1, 0], [0, 1]]), "repeats vertex"),
        (
            {"shape": "zone", "name": "slow", "kind": "speed_limit", "polygon": square(0, 0, 1)},
            "needs speed_limit and speed_unit",
        ),
        (
            {
                "shape": "zone",
                "name": "slow",
                "kind": "speed_limit",
                "polygon": square(0, 0, 1),
                "speed_limit": 150,
                "speed_unit": "percent",
            },
            "at most 100",
        ),
        (
            keep_out("fast", square(0, 0, 1), speed_limit=1.0, speed_unit="m/s"),
            "only speed_limit zones",
        ),
        (
            {"shape": "poi", "name": "x", "kind": "kiosk", "x": 0, "y": 0},
            "station, charger, door, note",
        ),
        ({"shape": "poi", "name": " ", "kind": "door", "x": 0, "y": 0}, "name must not be empty"),
        (
            {"shape": "poi", "name": "far", "kind": "door", "x": 1e12, "y": 0},
            "finite number of metres",
        ),
        ({"shape": "poi", "name": "no y", "kind": "door", "x": 1}, "needs the field 'y'"),
        ({**DOCK, "id": "has space"}, "annotation id"),
    ],
)
def test_a_bad_annotation_is_a_422_that_says_what_to_fix(body, says) -> None:
    w = World()
    r = w.create(body)
    assert r.status_code == 422, r.text
    assert says in r.text, r.text
    assert not w.publisher.records[w.settings.topic_annotation_events]


def test_conflicting_ids_and_unknown_ones_are_refused_with_a_reason() -> None:
    w = World()
    assert w.create({**DOCK, "id": "d"}).status_code == 201
    r = w.create({**DOCK, "id": "d"})
    assert r.status_code == 409 and "PUT" in r.json()["detail"]
    r = w.client.put("/api/v1/annotations/nope", json=DOCK, headers=w.as_(OPERATOR))
    assert r.status_code == 404 and "nope" in r.json()["detail"]
    r = w.client.delete("/api/v1/annotations/nope", headers=w.as_(OPERATOR))
    assert r.status_code == 404


# --- nav2 masks ------------------------------------------------------------------------


def _mask(w: World, filter_: str, at: int, **params) -> np.ndarray:
    r = w.client.get(
        f"/api/v1/costmap-filters/{filter_}/mask.pgm", params={"at": str(at), **params}
    )
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/x-portable-graymap"
    return np.asarray(Image.open(io.BytesIO(r.content)))


def _inside_brute(px: float, py: float, rings) -> bool:
    """Even-odd point in polygon, one point at a time (independent of the service's code)."""
    inside = False
    for ring in rings:
        n = len(ring)
        for i in range(n):
            (x0, y0), (x1, y1) = ring[i], ring[(i + 1) % n]
            if (y0 > py) != (y1 > py) and px < x0 + (py - y0) * (x1 - x0) / (y1 - y0):
                inside = not inside
    return inside


def _random_polygon(rng: random.Random, cx: float, cy: float, r: float) -> list[list[float]]:
    """A star-shaped (so simple) polygon of 3 to 12 vertices at sorted random angles."""
    n = rng.randint(3, 12)
    angles = sorted(rng.uniform(0, 2 * math.pi) for _ in range(n))
    return [
        [cx + rng.uniform(0.2, 1) * r * math.cos(a), cy + rng.uniform(0.2, 1) * r * math.sin(a)]
        for a in angles
    ]


def test_the_keep_out_mask_at_t_is_the_rasterisation_of_the_zones_at_t_pixel_for_pixel() -> None:
    """Random keep-out zones created over time (and one removed; speed and note zones never
    count): the mask at each instant equals an independent per-pixel test of each pixel
    centre against the zones standing then; aligned with the map (YAML origin, resolution)."""
    w = World()  # a 500 x 400 px map at 0.05 m, origin (-1.5, 2.0)
    ox, oy, res, width, height = -1.5, 2.0, 0.05, 500, 400
    rng = random.Random(36)
    standing: dict[str, list] = {}
    checks = []
    for step in range(8):
        polygon = _random_polygon(
            rng, ox + rng.uniform(2, 23), oy + rng.uniform(2, 18), rng.uniform(0.3, 4)
        )
        r = w.create(keep_out(f"z{step}", polygon))
        assert r.status_code == 201, r.text
        standing[r.json()["id"]] = polygon
        if step == 2:
            w.create(
                {
                    "shape": "zone",
                    "name": "slow",
                    "kind": "speed_limit",
                    "speed_limit": 30,
                    "speed_unit": "percent",
                    "polygon": square(ox + 1, oy + 1, 5),
                }
            )
            w.create(
                {
                    "shape": "zone",
                    "name": "note",
                    "kind": "note",
                    "polygon": square(ox + 10, oy + 10, 5),
                }
            )
        if step == 5:
            gone = next(iter(standing))
            assert (
                w.client.delete(f"/api/v1/annotations/{gone}", headers=w.as_(OPERATOR)).status_code
                == 204
            )
            del standing[gone]
        checks.append((w.clock.now_ms() + 10, [list(p) for p in standing.values()]))
        w.clock.advance(10_000)
    w.store_published()
    context_of(w.client.app).recent_edits.edits = []
    centres_x = ox + (np.arange(width) + 0.5) * res
    centres_y = oy + (height - np.arange(height) - 0.5) * res
    for t, polygons in (checks[3], checks[-1]):
        got = _mask(w, "keepout", t)
        assert got.shape == (height, width)
        want = np.full((height, width), 254, dtype=np.uint8)
        for p in polygons:
            xs, ys = [v[0] for v in p], [v[1] for v in p]
            cols = np.flatnonzero((centres_x >= min(xs)) & (centres_x <= max(xs)))
            rows = np.flatnonzero((centres_y >= min(ys)) & (centres_y <= max(ys)))
            for r_ in rows:
                for c in cols:
                    if _inside_brute(centres_x[c], centres_y[r_], [p]):
                        want[r_, c] = 0
        assert (got == want).all(), f"{int((got != want).sum())} pixels differ at {t}"
    doc = yaml.safe_load(w.client.get("/api/v1/costmap-filters/keepout/mask.yaml").text)
    assert doc["origin"][:2] == [ox, oy] and doc["resolution"] == res and doc["mode"] == "trinary"
    info = yaml.safe_load(w.client.get("/api/v1/costmap-filters/keepout/filter-info.yaml").text)
    params = info["keepout_filter_info_server"]["ros__parameters"]
    assert (params["type"], params["base"], params["multiplier"]) == (0, 0.0, 1.0)


def test_speed_masks_in_percent_and_metres_per_second_with_their_filter_info() -> None:
    """Percent: the mask value is the limit (type 1); m/s: limit = multiplier x value (type
    2), the fastest limit exact; overlapping zones keep the lowest limit; raw PGM."""
    w = World()
    ox, oy, res = -1.5, 2.0, 0.05
    for name, limit, unit, poly in (
        ("half", 50, "percent", square(ox + 1, oy + 1, 2)),
        ("crawl", 20, "percent", square(ox + 2, oy + 2, 2)),
        ("walk", 0.5, "m/s", square(ox + 10, oy + 10, 2)),
        ("run", 1.5, "m/s", square(ox + 11, oy + 11, 2)),
    ):
        assert (
            w.create(
                {
                    "shape": "zone",
                    "name": name,
                    "kind": "speed_limit",
                    "polygon": poly,
                    "speed_limit": limit,
                    "speed_unit": unit,
                }
            ).status_code
            == 201
        )
    later = NOW + 10  # the four edits are stamped NOW .. NOW + 3 (one per millisecond)
    pct = _mask(w, "speed", later, unit="percent")
    assert set(np.unique(pct).tolist()) == {0, 20, 50}
    h = pct.shape[0]

    def px(x: float, y: float) -> tuple[int, int]:
        return h - 1 - int((y - oy) / res), int((x - ox) / res)

    assert (
        pct[px(ox + 1.5, oy + 1.5)] == 50 and pct[px(ox + 2.5, oy + 2.5)] == 20
    )  # overlap: lowest
    assert pct[px(ox + 10.5, oy + 10.5)] == 0  # m/s zones are not in the percent mask
    mps = _mask(w, "speed", later, unit="m/s")
    info = yaml.safe_load(
        w.client.get(
            "/api/v1/costmap-filters/speed/filter-info.yaml",
            params={"unit": "m/s", "at": str(later)},
        ).text
    )["speed_filter_info_server"]["ros__parameters"]
    assert info["type"] == 2
    assert info["base"] + info["multiplier"] * mps[px(ox + 12.5, oy + 12.5)] == pytest.approx(1.5)
    # Another limit: rounded down to a step of the multiplier (never faster than set).
    walk = info["base"] + info["multiplier"] * mps[px(ox + 10.5, oy + 10.5)]
    assert 0.5 - info["multiplier"] < walk <= 0.5
    info = yaml.safe_load(w.client.get("/api/v1/costmap-filters/speed/filter-info.yaml").text)
    assert info["speed_filter_info_server"]["ros__parameters"]["type"] == 1
    assert (
        yaml.safe_load(w.client.get("/api/v1/costmap-filters/speed/mask.yaml").text)["mode"]
        == "raw"
    )


def test_a_map_without_geometry_has_no_mask_and_says_why() -> None:
    from mapservice.core.events import MapMetaSet

    w = World(make_envelope("admin", NOW - 1000, NOW - 1000, MapMetaSet(100, 100, 100, 100, 1, 1)))
    r = w.client.get("/api/v1/costmap-filters/keepout/mask.pgm")
    assert r.status_code == 409 and "resolution and origin" in r.json()["detail"]


@pytest.mark.skipif(not KEEPOUT_YAML.exists(), reason="the shared warehouse maps are not here")
def test_the_warehouse_keep_out_mask_imported_and_exported_gives_the_same_pixels() -> None:
    """nav2's own keep-out mask for the warehouse, imported as zones (one per connected
    area, with holes) and exported: the same keep-out pixels, and every other pixel free."""
    source = load_ros_map(KEEPOUT_YAML)
    floor = load_ros_map(KEEPOUT_YAML.with_name("warehouse.yaml"))
    # The 1.7 MB PGM in base64 is over the default body limit (1 MiB): a deployment that
    # imports such masks raises MAPSERVICE_API_MAX_BODY_BYTES, or sends the PNG (lossless).
    w = World(
        make_envelope("admin", NOW - 1000, NOW - 1000, meta_for(floor)),
        api_max_body_bytes=4_000_000,
    )
    body = {
        "yaml": KEEPOUT_YAML.read_text(),
        "name": "warehouse keep-out",
        "image_base64": base64.b64encode(
            KEEPOUT_YAML.with_name("warehouse_keepout.pgm").read_bytes()
        ).decode(),
    }
    r = w.client.post("/api/v1/annotations/import-mask", json=body, headers=w.as_(OPERATOR))
    assert r.status_code == 201, r.text
    events = w.store_published()
    assert len(events) == len(r.json()["ids"]) > 1
    assert all(
        isinstance(e.payload, AnnotationCreated) and e.payload.annotation.kind == "keep_out"
        for e in events
    )
    context_of(w.client.app).recent_edits.edits = []
    # One event per zone, a millisecond apart: the mask as of the import's last one.
    exported = _mask(w, "keepout", r.json()["at_ms"])
    want = classify(source) == 100
    assert ((exported == 0) == want).all(), int(((exported == 0) != want).sum())
    assert set(np.unique(exported).tolist()) == {0, 254}
    doc = yaml.safe_load(w.client.get("/api/v1/costmap-filters/keepout/mask.yaml").text)
    assert doc["resolution"] == source.resolution and doc["origin"] == list(source.origin)
    # A mask that does not lie over the map is refused, saying why.
    small = io.BytesIO()
    Image.fromarray(np.zeros((10, 10), dtype=np.uint8)).save(small, format="PNG")
    r = w.client.post(
        "/api/v1/annotations/import-mask",
        headers=w.as_(OPERATOR),
        json={**body, "image_base64": base64.b64encode(small.getvalue()).decode()},
    )
    assert r.status_code == 422 and "10 x 10 px but the map is 1006 x 1674" in r.text
    r = w.client.post(
        "/api/v1/annotations/import-mask",
        headers=w.as_(OPERATOR),
        json={**body, "image_base64": "not base64!"},
    )
    assert r.status_code == 422


def test_removal_events_round_trip_through_the_envelope() -> None:
    e = make_envelope("operator:ab", NOW, NOW, AnnotationRemoved("z", "operator:ab"))
    from mapservice.core.events import encode

    assert decode(encode(e)) == e and e.type == "annotation.removed"
