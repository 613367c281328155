"""/api/v1/robots in pages: `limit` robots in robotId order and a `next_after` cursor, one
page of everything by default (what the replay UI asks for)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import pose_event

NOW = 1_795_255_200_000


def client(robots: int) -> TestClient:
    store = MemoryStore()
    store.append([pose_event(f"r{i:03d}", NOW - 1000 + i) for i in range(robots)])
    return TestClient(create_app(Settings(), store, {}, ManualClock(NOW)))


def test_pages_follow_the_cursor_to_every_robot_once() -> None:
    """25 robots in pages of 10: 10, 10, 5, each page after the previous one's cursor."""
    c = client(25)
    seen, after, pages = [], None, 0
    while True:
        params = {"at": NOW, "limit": 10} | ({"after": after} if after else {})
        page = c.get("/api/v1/robots", params=params).json()
        pages += 1
        seen += [r["robotId"] for r in page["robots"]]
        after = page["next_after"]
        if after is None:
            break
        assert after == seen[-1]
    assert pages == 3 and seen == [f"r{i:03d}" for i in range(25)]


def test_the_default_is_one_page_of_every_robot() -> None:
    """Without `limit` a fleet of up to 10,000 comes whole, with no cursor (the UI's call)."""
    body = client(25).get("/api/v1/robots", params={"at": NOW}).json()
    assert len(body["robots"]) == 25 and body["next_after"] is None


def test_bad_page_parameters_are_422() -> None:
    c = client(1)
    for params in ({"limit": 0}, {"limit": 10_001}, {"after": "x" * 65}):
        reply = c.get("/api/v1/robots", params=params)
        assert reply.status_code == 422, params
