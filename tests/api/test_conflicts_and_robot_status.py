"""GET /api/v1/conflicts, and the online / clock-skew fields of the robots at T."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.ports import ConflictRow
from mapservice.core.wire2019 import content_hash
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
PA, PB = bytes(10_000), bytes([254]) * 10_000
HA, HB = content_hash(PA).hex(), content_hash(PB).hex()


@pytest.fixture
def store(ev) -> MemoryStore:
    s = MemoryStore()
    s.append(
        [
            ev.pose("steady", NOW - 10_000, receive_lag_ms=40),
            ev.pose("skewed", NOW - 2_000, receive_lag_ms=-7_000),  # its clock runs 7 s ahead
            ev.pose("silent", NOW - 10_001, receive_lag_ms=5_000),
        ]
    )
    s.append(
        [
            ev.chunk("a", NOW - 9_000, 1, 2, PA),
            ev.chunk("b", NOW - 5_000, 1, 2, PB),
            ev.chunk("b", NOW - 1_500, 0, 0, PB),
            ev.chunk("c", NOW - 1_000, 0, 0, PA),
            ev.chunk("d", NOW - 1_200, 0, 0, PB),
        ]
    )
    s.append_conflicts(
        [
            ConflictRow(1, 2, NOW - 5_000, "a", NOW - 9_000, "b"),
            ConflictRow(0, 0, NOW - 1_000, "d", NOW - 1_200, "c"),
        ]
    )
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(NOW)), raise_server_exceptions=False
    )


def test_robots_at_carry_online_and_clock_skew(client) -> None:
    """online is age <= robot_offline_after_s; skew is receive - event time, flagged beyond 5 s."""
    body = client.get("/api/v1/robots", params={"at": NOW}).json()
    got = {
        r["robotId"]: (r["online"], r["clock_skew_ms"], r["clock_skew_flag"])
        for r in body["robots"]
    }
    assert got == {
        "steady": (True, 40, False),
        "skewed": (True, -7_000, True),
        "silent": (False, 5_000, False),
    }


@pytest.mark.parametrize(
    ("states", "at", "online"),
    [
        ([], 0, True),
        ([("OFFLINE", -500)], 0, False),  # at once, not when its last pose ages out
        ([("OFFLINE", -500)], -501, True),
        ([("CONNECTIONBROKEN", -500)], 0, False),
        ([("OFFLINE", -800), ("ONLINE", -200)], 0, True),  # back online
        ([("ONLINE", -200)], 9_001, False),  # online, but silent too long
        ([("OFFLINE", -3_600_000)], 0, True),  # a state of more than an hour ago
        ([("OFFLINE", -3_600_000)], -1, False),
    ],
)
def test_a_vehicle_is_offline_at_an_instant_by_its_connection_state(ev, states, at, online):
    """A VDA 5050 vehicle's latest connection state of the hour before the instant makes it
    offline (OFFLINE, CONNECTIONBROKEN) even while its last pose is recent."""
    from tests.mapservice.core.event_history import connection

    store = MemoryStore()
    store.append([ev.pose("Acme:1", NOW - 1_000), ev.pose("plain", NOW - 1_000)])
    store.append([connection("Acme:1", NOW + dt, state) for state, dt in states])
    client = TestClient(create_app(Settings(), store, {}, ManualClock(NOW + 60_000)))
    body = client.get("/api/v1/robots", params={"at": NOW + at}).json()
    got = {r["robotId"]: r["online"] for r in body["robots"]}
    assert got == {"Acme:1": online, "plain": at <= 9_000}


def test_robot_thresholds_come_from_settings(store) -> None:
    """The offline and skew thresholds are the settings'."""
    app = create_app(
        Settings(robot_offline_after_s=1, clock_skew_threshold_s=10), store, {}, ManualClock(NOW)
    )
    robots = TestClient(app).get("/api/v1/robots", params={"at": NOW}).json()["robots"]
    assert [(r["online"], r["clock_skew_flag"]) for r in robots] == [(False, False)] * 3


def test_conflicts_in_window_ordered(client) -> None:
    """/api/v1/conflicts lists the conflicts with from <= ts < to, in time order, with
    both writes' content hashes from the chunk history."""
    body = client.get("/api/v1/conflicts", params={"from": NOW - 60_000, "to": NOW}).json()
    assert body["truncated"] is False and body["window_s"] == 60.0
    assert body["conflicts"] == [
        {
            "row": 1,
            "column": 2,
            "ts_ms": NOW - 5_000,
            "robot_a": "a",
            "ts_a_ms": NOW - 9_000,
            "hash_a": HA,
            "robot_b": "b",
            "hash_b": HB,
            "seek_ms": NOW - 4_999,
        },
        {
            "row": 0,
            "column": 0,
            "ts_ms": NOW - 1_000,
            "robot_a": "d",
            "ts_a_ms": NOW - 1_200,
            "hash_a": HB,
            "robot_b": "c",
            "hash_b": HA,
            "seek_ms": NOW - 999,
        },
    ]
    body = client.get("/api/v1/conflicts", params={"from": NOW - 60_000, "to": NOW - 1_000}).json()
    assert len(body["conflicts"]) == 1
    body = client.get(
        "/api/v1/conflicts", params={"from": NOW - 60_000, "to": NOW, "limit": 1}
    ).json()
    assert body["truncated"] is True and len(body["conflicts"]) == 1


def test_the_inspector_gets_both_writes_and_lands_after_the_later_one(store) -> None:
    """One call gives what the conflict inspector shows: both writes' robots, times and
    pixels (a PNG per content hash), and a seek time at which the map holds the later
    write. A row naming the map uploader (recorded before uploads were left out) is not
    listed."""
    store.append_conflicts([ConflictRow(1, 2, NOW - 8_000, "map-upload", NOW - 8_500, "a")])
    client = TestClient(create_app(Settings(), store, {}, ManualClock(NOW)))
    body = client.get("/api/v1/conflicts", params={"from": NOW - 60_000, "to": NOW}).json()
    assert "map upload" in body["rule"] and "60 s" in body["rule"]
    assert [(c["robot_a"], c["robot_b"]) for c in body["conflicts"]] == [("a", "b"), ("d", "c")]
    first = body["conflicts"][0]
    for h in (first["hash_a"], first["hash_b"]):
        png = client.get(f"/api/v1/chunk-contents/{h}", params={"encoding": "png"})
        assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    seen = {(c.row, c.column): c.content_hash for c in store.map_at(first["seek_ms"])}
    assert seen[(1, 2)] == first["hash_b"]
    assert {(c.row, c.column): c.content_hash for c in store.map_at(first["ts_ms"] - 1)}[
        (1, 2)
    ] == first["hash_a"]


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"from": NOW, "to": NOW - 1}, "swap"),
        ({"from": "yesterday", "to": NOW}, "ISO 8601"),
        ({"from": NOW - 8 * 86_400_000, "to": NOW}, "split"),
    ],
)
def test_bad_conflict_windows_are_400_with_a_reason(client, params, fragment) -> None:
    """from > to, unparseable times and spans beyond the retention get a 400 saying why."""
    r = client.get("/api/v1/conflicts", params=params)
    assert r.status_code == 400 and fragment in r.json()["detail"]


def test_conflicts_need_from_and_to(client) -> None:
    """Missing parameters are a 422 naming them."""
    r = client.get("/api/v1/conflicts")
    assert r.status_code == 422 and "from" in r.text


def test_a_vda_vehicles_facts(ev) -> None:
    """/api/v1/robots/{id}/vda5050: errors, connection states (offline at the last will's
    receipt), the factsheet, and both names; a robot id that is no vehicle's is a 404."""
    from mapservice.core.events import decode
    from mapservice.core.intake import Intake
    from mapservice.ingest.router import Router
    from tests.fixtures import vda5050 as vda

    router, store = Router(Settings(), "gw"), MemoryStore()
    m, s = "Acme Co", "7:1"
    for subtopic, msg, received in [
        ("connection", vda.connection("2.0.0", m, s, NOW - 9_000, "ONLINE"), NOW - 9_000),
        ("factsheet", vda.factsheet("2.0.0", m, s, NOW - 8_000), NOW - 8_000),
        (
            "state",
            vda.state("2.0.0", m, s, NOW - 7_000, errors=(("FATAL", "bumper", "hit"),)),
            NOW - 7_000,
        ),
        ("connection", vda.connection("2.0.0", m, s, NOW - 9_000, "CONNECTIONBROKEN"), NOW - 2_000),
    ]:
        record = router.route(f"uagv/v2/{m}/{s}/{subtopic}", vda.encode(msg), received, Intake())
        store.append([decode(record.value)])
    client = TestClient(create_app(Settings(), store, {}, ManualClock(NOW)))
    body = client.get("/api/v1/robots/Acme@20Co:7@3A1/vda5050").json()
    assert (body["manufacturer"], body["serialNumber"], body["online"]) == (m, s, False)
    assert [(c["state"], c["ts_ms"]) for c in body["connections"]] == [
        ("ONLINE", NOW - 9_000),
        ("CONNECTIONBROKEN", NOW - 2_000),
    ]
    assert [(e["level"], e["type"], e["description"]) for e in body["errors"]] == [
        ("FATAL", "bumper", "hit")
    ]
    assert body["factsheet"]["factsheet"]["serialNumber"] == s
    early = client.get("/api/v1/robots/Acme@20Co:7@3A1/vda5050", params={"to": NOW - 7_500}).json()
    assert early["online"] is True and early["errors"] == []
    missing = client.get("/api/v1/robots/plain-robot/vda5050")
    assert missing.status_code == 404 and "manufacturer" in missing.json()["detail"]


def test_the_vda_fleets_facts() -> None:
    """/api/v1/robots/vda5050: every vehicle with facts in the window, its errors and the
    state that cleared them, its online state and factsheet; 2019 robots are not in it."""
    from mapservice.core.events import decode
    from mapservice.core.intake import Intake
    from mapservice.ingest.router import Router
    from tests.fixtures import vda5050 as vda

    router, store = Router(Settings(), "gw"), MemoryStore()
    for m, s, subtopic, msg in [
        (
            "Acme",
            "1",
            "state",
            vda.state(
                "2.0.0", "Acme", "1", NOW - 7_000, errors=(("WARNING", "lowBattery", "charge me"),)
            ),
        ),
        ("Acme", "1", "state", vda.state("2.0.0", "Acme", "1", NOW - 6_000)),
        ("Beta", "2", "factsheet", vda.factsheet("2.0.0", "Beta", "2", NOW - 6_000)),
        ("Beta", "2", "connection", vda.connection("2.0.0", "Beta", "2", NOW - 5_000, "OFFLINE")),
    ]:
        record = router.route(f"uagv/v2/{m}/{s}/{subtopic}", vda.encode(msg), NOW - 5_000, Intake())
        store.append([decode(record.value)])
    client = TestClient(create_app(Settings(), store, {}, ManualClock(NOW)))
    body = {v["robotId"]: v for v in client.get("/api/v1/robots/vda5050").json()}
    assert sorted(body) == ["Acme:1", "Beta:2"]
    assert [
        (e["level"], e["type"], e["description"], e["ts_ms"]) for e in body["Acme:1"]["errors"]
    ] == [("WARNING", "lowBattery", "charge me", NOW - 7_000)]
    assert body["Acme:1"]["errorClears"] == [NOW - 6_000] and body["Acme:1"]["online"] is None
    assert (
        body["Beta:2"]["online"] is False
        and body["Beta:2"]["factsheet"]["factsheet"]["manufacturer"] == "Beta"
    )
    assert (
        client.get("/api/v1/robots/vda5050", params={"to": NOW - 6_500}).json()[0]["errorClears"]
        == []
    )
    assert client.get("/api/v1/robots/vda5050", params={"limit": 0}).status_code == 422
