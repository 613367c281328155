"""GET /api/v1/incidents: the incidents the processors found, as the rules found them over
the stored poses, meeting the window, filtered by kind and robot; an ongoing silence read
as of now; bad filters refused with a message."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.incidents import detect
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000
PATH = ((1.0, 1.0), (5.0, 1.0))


@pytest.fixture
def store(ev) -> MemoryStore:
    """Over the last two minutes: s stuck for 40 s, a passing b at 0.4 m, c's battery low,
    d silent since 30 s ago."""
    s = MemoryStore()
    t0 = NOW - 120_000
    events = []
    for k in range(100):
        t = t0 + k * 1000
        events += [
            ev.pose("s", t, 3.0 if k < 60 else 3.0 + (k - 60) * 0.5, 3.0, path=PATH),
            ev.pose("a", t, k * 0.5, 10.0),
            ev.pose("b", t, 25.0, 10.4),
            ev.pose("c", t, 40.0, 40.0, battery_level=30.0 - k * 0.25),
        ]
        if k < 90:
            events.append(ev.pose("d", t, 50.0, 50.0))
    s.append(events)
    s.append_incidents(detect(s.poses(0, NOW, limit=10**9), NOW - 20_000), NOW - 20_000)
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(NOW)), raise_server_exceptions=False
    )


def test_the_found_incidents_meet_the_window_by_start(client) -> None:
    body = client.get("/api/v1/incidents", params={"from": NOW - 120_000, "to": NOW}).json()
    kinds = [(i["kind"], i["robots"]) for i in body["incidents"]]
    assert ("stuck", ["s"]) in kinds and ("near_miss", ["a", "b"]) in kinds
    assert ("battery_low", ["c"]) in kinds and ("offline", ["d"]) in kinds
    starts = [i["start_ms"] for i in body["incidents"]]
    assert starts == sorted(starts) and not body["truncated"]
    near = next(i for i in body["incidents"] if i["kind"] == "near_miss")
    assert near["measure"] == pytest.approx(0.4, abs=1e-3)
    assert {e["robotId"] for e in near["evidence"]} == {"a", "b"}


def test_an_ongoing_silence_lasts_until_now(client) -> None:
    body = client.get(
        "/api/v1/incidents", params={"from": NOW - 60_000, "to": NOW, "kind": "offline"}
    ).json()
    (silence,) = body["incidents"]
    assert silence["robots"] == ["d"] and silence["ongoing"]
    assert silence["end_ms"] == NOW  # found 20 s ago, read now
    assert silence["measure"] == (NOW - silence["start_ms"]) / 1000


@pytest.mark.parametrize(
    ("params", "kinds"),
    [
        ({"kind": ["stuck", "battery_low"]}, {"stuck", "battery_low"}),
        ({"robot": "a"}, {"near_miss"}),
        ({"robot": "nobody"}, set()),
    ],
)
def test_filters_by_kind_and_robot(client, params, kinds) -> None:
    body = client.get(
        "/api/v1/incidents", params={"from": NOW - 120_000, "to": NOW, **params}
    ).json()
    assert {i["kind"] for i in body["incidents"]} == kinds


@pytest.mark.parametrize(
    "params",
    [
        {"kind": "collision"},
        {"limit": 0},
        {"limit": 100_001},
        {"robot": "r" * 257},
        {"from": "yesterday"},
    ],
)
def test_bad_filters_are_refused_with_a_message(client, params) -> None:
    r = client.get("/api/v1/incidents", params={"from": NOW - 120_000, "to": NOW, **params})
    assert r.status_code in (400, 422) and r.json()["detail"]


def test_the_limit_truncates(client) -> None:
    body = client.get(
        "/api/v1/incidents", params={"from": NOW - 120_000, "to": NOW, "limit": 1}
    ).json()
    assert len(body["incidents"]) == 1 and body["truncated"]


def test_the_page_is_the_documented_model_field_for_field(client) -> None:
    """The page is encoded without pydantic models: it must still be exactly what the
    OpenAPI model (`Incidents`) documents, every field in its order, none more."""
    from mapservice.api.routers.incidents import Incident, Incidents

    reply = client.get("/api/v1/incidents", params={"from": NOW - 120_000, "to": NOW})
    assert reply.status_code == 200 and reply.headers["content-type"] == "application/json"
    body = reply.json()
    model = Incidents.model_validate(body, strict=True)
    assert body == model.model_dump(mode="json") and len(body["incidents"]) >= 4
    assert list(body) == list(Incidents.model_fields)
    assert all(list(i) == list(Incident.model_fields) for i in body["incidents"])
