"""Who may move the floor: the map's frame (size, chunk grid, resolution, origin) changes
only with the admin's token. Every frame field changed alone, by every role, in both read
modes: the admin's change is published, everyone else's is refused (403 naming the field,
401 without a credential) and nothing reaches Kafka; the held frame re-posted (as a 2019
robot does at start-up, with or without resolution and origin) stays a writer's right."""

from __future__ import annotations

from dataclasses import replace

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.api.context import context_of
from mapservice.api.posted_meta import PostedMeta
from mapservice.core.events import MapMetaSet, decode, make_envelope
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.api.access_kit import NOW, auth, settings_for

HELD = MapMetaSet(
    width=500,
    height=400,
    chunk_width=100,
    chunk_height=100,
    chunk_rows=4,
    chunk_cols=5,
    comment="the warehouse",
    resolution=0.05,
    origin=(-1.5, 2.0, 0.0),
)
HELD_DOC = HELD.to_2019()

# Each a change of one frame field alone, still a meta.json that parses (chunks cover it).
FRAME_CHANGES = {
    "width": {"width": 450},
    "height": {"height": 350},
    "chunk_width": {"CHUNK_WIDTH": 120},
    "chunk_height": {"CHUNK_HEIGHT": 110},
    "chunk_rows": {"CHUNK_ROWS": 5},
    "chunk_cols": {"CHUNK_COLS": 6},
    "resolution": {"resolution": 0.1},
    "resolution (rounding)": {"resolution": 0.05000001},
    "origin x": {"origin": [10.0, 2.0, 0.0]},
    "origin y": {"origin": [-1.5, -2.0, 0.0]},
    "origin yaw": {"origin": [-1.5, 2.0, 0.3]},
}
REFUSED = {"writer": 403, "robot": 403, "operator": 403, "reader": 403, "none": 401}


@pytest.fixture(scope="module")
def apps() -> dict[str, FastAPI]:
    """One app per read mode for the whole module, built by its first case (inside the
    cases' hermetic environment, tests/conftest.py): building one takes a tenth of a second,
    a case a few milliseconds. Each case starts from a fresh publisher and PostedMeta
    (_world), and nothing else a case does changes what the next one sees: the store only
    ever holds the meta it is built with (writes go to the publisher)."""
    return {}


def _world(apps: dict[str, FastAPI], read_access: str) -> tuple[TestClient, MemoryPublisher, str]:
    """The shared app of this read mode as a new one would be: the meta its last case
    published forgotten (else it would stand in for the held one for a minute) and a
    publisher that has published nothing."""
    if read_access not in apps:
        store = MemoryStore()
        store.append([make_envelope("admin", NOW - 60_000, NOW - 60_000, HELD)])
        apps[read_access] = create_app(settings_for(read_access), store, {}, ManualClock(NOW))
    app = apps[read_access]
    publisher = MemoryPublisher()
    context = replace(context_of(app), publisher=publisher, posted_meta=PostedMeta())
    app.state.context = context
    assert context.roles is not None and context.roles.history.latest_meta() == HELD
    return TestClient(app), publisher, context.settings.topic_meta_events


def _published(publisher: MemoryPublisher, topic: str) -> list[MapMetaSet]:
    publisher.poll()
    return [decode(value).payload for _, value in publisher.records.get(topic, [])]


@pytest.mark.parametrize("read_access", ["open", "token"])
@pytest.mark.parametrize("method", ["POST", "PUT"])
@pytest.mark.parametrize("field", list(FRAME_CHANGES))
@pytest.mark.parametrize("role", [*REFUSED, "admin"])
def test_a_frame_change_needs_the_admin(apps, read_access, method, field, role) -> None:
    client, publisher, topic = _world(apps, read_access)
    body = {**HELD_DOC, **FRAME_CHANGES[field]}
    r = client.request(method, "/api/chunk-service/meta", json=body, headers=auth(role))
    if role == "admin":
        assert r.status_code == 200, r.text
        [stored] = _published(publisher, topic)
        assert stored == MapMetaSet.from_2019(body)
        return
    assert r.status_code == REFUSED[role], r.text
    if role in ("writer", "robot"):
        name = field.split(" ")[0]
        assert name.replace("origin", "origin from") in r.json()["detail"]
        assert "MAPSERVICE_ADMIN_TOKEN" in r.json()["detail"]
    assert _published(publisher, topic) == []


@pytest.mark.parametrize("read_access", ["open", "token"])
@pytest.mark.parametrize("role", ["writer", "robot", "admin"])
def test_the_held_frame_re_posted_is_a_writers_right_and_moves_nothing(
    apps, read_access, role
) -> None:
    """The same meta; the same without resolution and origin (a 2019 robot's meta.json),
    which keeps the held ones; another comment or max_brightness (not the frame)."""
    client, publisher, topic = _world(apps, read_access)
    without_frame = {k: v for k, v in HELD_DOC.items() if k not in ("resolution", "origin")}
    for body in (HELD_DOC, without_frame, {**HELD_DOC, "comment": "re-scanned"}):
        r = client.post("/api/chunk-service/meta", json=body, headers=auth(role))
        assert r.status_code == 200, r.text
    stored = _published(publisher, topic)
    assert [(m.resolution, m.origin) for m in stored] == [(0.05, (-1.5, 2.0, 0.0))] * 3
