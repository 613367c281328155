"""GET /api/v1/map?layout=compact: the map at T as arrays (what the replay UI asks for on a seek)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000
PIXELS = bytes(i % 256 for i in range(100 * 100))


@pytest.fixture
def client(ev) -> TestClient:
    store = MemoryStore()
    store.append(
        [
            ev.chunk("r1", NOW + 500, 3, 2, PIXELS),
            ev.chunk("r2", NOW + 1500, 0, 1, PIXELS),
            ev.chunk("r2", NOW + 2000, 0, 1, bytes(10_000)),
        ]
    )
    return TestClient(create_app(Settings(), store, {}, ManualClock(NOW + 60_000)))


def test_compact_layout_holds_what_the_rows_hold(client) -> None:
    """layout=compact lists the same chunks as the default rows, one array per chunk in `fields` order."""
    rows = client.get("/api/v1/map", params={"at": NOW + 2000}).json()
    compact = client.get("/api/v1/map", params={"at": NOW + 2000, "layout": "compact"}).json()
    assert compact["at_ms"] == rows["at_ms"] and compact["meta"] == rows["meta"]
    assert "chunks" not in compact
    assert compact["fields"] == ["row", "column", "ts_ms", "robotId", "content_hash"]
    as_rows = [dict(zip(compact["fields"], cell)) for cell in compact["cells"]]
    assert as_rows == [{k: v for k, v in c.items() if k != "timestamp"} for c in rows["chunks"]]
    assert {(c["row"], c["column"]): c["ts_ms"] for c in as_rows} == {
        (0, 1): NOW + 2000,
        (3, 2): NOW + 500,
    }


def test_rows_layout_keeps_the_2019_timestamps(client) -> None:
    """The default layout still carries each chunk's 2019-style timestamp, milliseconds only when non-zero."""
    chunks = client.get("/api/v1/map", params={"at": NOW + 2000}).json()["chunks"]
    assert {c["timestamp"] for c in chunks} == {"2026-11-21T10:00:00.500", "2026-11-21T10:00:02"}


def test_unknown_layout_is_422(client) -> None:
    """A layout other than rows or compact is refused with a message naming the choices."""
    r = client.get("/api/v1/map", params={"at": NOW, "layout": "columns"})
    assert r.status_code == 422 and "compact" in r.text
