"""A history store refusing inserts is told the truth: /readyz names it and why, and
GET /api/v1/status gives the replay UI "history not stored since ..."."""

from __future__ import annotations

from fastapi.testclient import TestClient

from mapservice.api.app import create_app
from mapservice.runtime.insert_health import InsertHealth
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

FULL = "Code: 243. DB::Exception: Cannot reserve 1.00 MiB, not enough space. (NOT_ENOUGH_SPACE)"


def client_with(health: InsertHealth | None) -> TestClient:
    readiness = {"clickhouse": lambda: True}
    if health is not None:
        readiness["history_store"] = health
    app = create_app(
        Settings(),
        MemoryStore(),
        readiness,
        history_status=None if health is None else health.status,
    )
    return TestClient(app)


def test_readiness_is_false_naming_the_failing_inserts_and_ready_again_after() -> None:
    """ClickHouse answers SELECT 1 but refuses inserts: /readyz 503, history_store false,
    the reason with the error code; the next successful insert makes it 200 again."""
    health = InsertHealth()
    client = client_with(health)
    assert client.get("/readyz").json() == {
        "ok": True,
        "checks": {"clickhouse": True, "history_store": True},
    }
    health.failed(RuntimeError(FULL))
    reply = client.get("/readyz")
    body = reply.json()
    assert reply.status_code == 503 and body["ok"] is False
    assert body["checks"] == {"clickhouse": True, "history_store": False}
    assert body["reasons"]["history_store"].startswith("inserts failing since ")
    assert "NOT_ENOUGH_SPACE" in body["reasons"]["history_store"]
    health.stored()
    assert (
        client.get("/readyz").status_code == 200 and "reasons" not in client.get("/readyz").json()
    )


def test_status_says_whether_the_history_is_stored_and_since_when_not() -> None:
    """The UI's source: storing, since when not, the last stored insert, the reason."""
    health = InsertHealth()
    client = client_with(health)
    health.stored()
    body = client.get("/api/v1/status").json()["history"]
    assert body["storing"] is True and body["reason"] is None and body["last_stored_ms"] > 0
    health.failed(RuntimeError(FULL))
    body = client.get("/api/v1/status").json()["history"]
    assert body["storing"] is False and body["failing_since_ms"] >= body["last_stored_ms"]
    assert "NOT_ENOUGH_SPACE" in body["reason"]


def test_an_api_without_the_processors_says_it_does_not_know() -> None:
    """The API running apart from the processors does not store the history: null, not a guess."""
    reply = client_with(None).get("/api/v1/status")
    assert reply.status_code == 200 and reply.json() == {"history": None}
