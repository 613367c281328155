"""Operators' commands through the API: who may send them (readers and robots refused,
saying why), the event on the command topic with who sent it, unknown robots and points
of interest refused with a message, and the history of commands with the robots' acks
and outcomes over a window."""

from __future__ import annotations

from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.commands import CommandAcknowledged, CommandFinished, CommandIssued
from mapservice.core.events import PoseReported, decode, make_envelope
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import meta_event

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
OPERATOR = "operator-" + "p" * 32
READER = "viewer-" + "r" * 32
ROBOT = "robot-" + "o" * 32
ADMIN = "admin-" + "a" * 32


class World:
    def __init__(self) -> None:
        self.settings = Settings(
            api_operator_tokens=OPERATOR,
            api_reader_tokens=READER,
            api_robot_tokens=f"agv-1={ROBOT}",
            api_rate_limit="",
            admin_token=ADMIN,
        )
        self.store = MemoryStore()
        self.store.append(
            [
                meta_event(NOW - 86_400_000),
                make_envelope(
                    "agv-1",
                    NOW - 5_000,
                    NOW - 5_000,
                    PoseReported((1.0, 2.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
                ),
            ]
        )
        self.clock = ManualClock(NOW)
        self.publisher = MemoryPublisher()
        self.client = TestClient(
            create_app(self.settings, self.store, {}, self.clock, publisher=self.publisher)
        )

    def send(self, body: dict, token: str | None = OPERATOR):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        return self.client.post("/api/v1/commands", json=body, headers=headers)

    def published(self) -> list:
        return [
            decode(v) for _, v in self.publisher.records.get(self.settings.topic_command_events, [])
        ]

    def store_published(self) -> None:
        self.store.append(self.published())


def test_readers_robots_and_strangers_may_not_send_commands_and_are_told_why() -> None:
    w = World()
    pause = {"robotId": "agv-1", "kind": "pause"}
    r = w.send(pause, READER)
    assert r.status_code == 403 and "commanding robots" in r.json()["detail"]
    assert "MAPSERVICE_API_OPERATOR_TOKENS" in r.json()["detail"]
    r = w.send(pause, ROBOT)  # a robot may not command itself or others
    assert r.status_code == 403 and "this robot token may not" in r.json()["detail"]
    assert "needs an operator or admin token" in r.json()["detail"]
    r = w.send(pause, None)
    assert r.status_code == 401 and "Authorization: Bearer" in r.json()["detail"]
    assert w.published() == []
    assert w.send(pause, ADMIN).status_code == 202


def test_a_command_is_an_event_with_who_sent_it_keyed_by_its_robot() -> None:
    w = World()
    r = w.send({"robotId": "agv-1", "kind": "pause", "id": "c-1"})
    assert r.status_code == 202, r.text
    out = r.json()
    assert out["commandId"] == "c-1" and out["kind"] == "pause" and out["issued_ms"] == NOW
    assert out["issuedBy"].startswith("operator") and OPERATOR not in out["issuedBy"]
    ((key, _),) = w.publisher.records[w.settings.topic_command_events]
    assert key == b"agv-1"
    (event,) = w.published()
    assert event.payload == CommandIssued("c-1", "agv-1", "pause", out["issuedBy"], NOW)
    assert event.robot_id == "agv-1" and event.event_time_ms == NOW


def test_goto_poi_carries_the_points_position_and_unknowns_are_refused() -> None:
    w = World()
    r = w.client.post(
        "/api/v1/annotations",
        json={
            "id": "dock-1",
            "shape": "poi",
            "name": "dock",
            "kind": "station",
            "x": 3.5,
            "y": 4.0,
            "heading": 1.5,
        },
        headers={"Authorization": f"Bearer {OPERATOR}"},
    )
    assert r.status_code == 201, r.text
    w.store.append([decode(v) for _, v in w.publisher.records[w.settings.topic_annotation_events]])
    r = w.send({"robotId": "agv-1", "kind": "goto_poi", "poiId": "dock-1"})
    assert r.status_code == 202, r.text
    assert r.json()["target"] == {"x": 3.5, "y": 4.0, "heading": 1.5}
    assert w.published()[-1].payload.x == 3.5
    r = w.send({"robotId": "agv-9", "kind": "pause"})
    assert (
        r.status_code == 404
        and "agv-9" in r.json()["detail"]
        and "GET /api/v1/robots" in r.json()["detail"]
    )
    r = w.send({"robotId": "agv-1", "kind": "goto_poi", "poiId": "nowhere"})
    assert r.status_code == 404 and "nowhere" in r.json()["detail"]
    r = w.send({"robotId": "agv-1", "kind": "goto_poi"})
    assert r.status_code == 422 and "poiId" in r.json()["detail"]
    r = w.send({"robotId": "agv-1", "kind": "pause", "poiId": "dock-1"})
    assert r.status_code == 422 and "only goto_poi" in r.json()["detail"]
    for bad in (
        {"robotId": "agv-1", "kind": "explode"},
        {"robotId": "a/#", "kind": "pause"},
        {"robotId": "agv-1", "kind": "pause", "id": "bad id!"},
    ):
        r = w.send(bad)
        assert r.status_code == 422, (bad, r.text)
    assert len(w.published()) == 1


def test_commands_with_their_acks_and_outcomes_over_a_window() -> None:
    w = World()
    assert w.send({"robotId": "agv-1", "kind": "pause", "id": "c-1"}).status_code == 202
    w.store_published()
    w.store.append(
        [
            make_envelope(
                "agv-1", NOW + 200, NOW + 210, CommandAcknowledged("c-1", "agv-1", "accepted")
            ),
            make_envelope("agv-1", NOW + 900, NOW + 910, CommandFinished("c-1", "agv-1", "done")),
            # another robot's answer to agv-1's command never counts as agv-1's
            make_envelope(
                "agv-2", NOW + 300, NOW + 310, CommandAcknowledged("c-1", "agv-2", "rejected", "x")
            ),
        ]
    )
    r = w.client.get("/api/v1/commands", params={"from": str(NOW - 1000), "to": str(NOW + 5000)})
    assert r.status_code == 200, r.text
    (c,) = r.json()["commands"]
    assert c["commandId"] == "c-1" and c["issuedBy"].startswith("operator")
    assert c["ack"] == {"ts_ms": NOW + 200, "status": "accepted", "reason": ""}
    assert c["outcome"] == {"ts_ms": NOW + 900, "status": "done", "reason": ""}
    # At a playhead before the outcome, the command shows only its ack.
    r = w.client.get("/api/v1/commands", params={"from": str(NOW - 1000), "to": str(NOW + 500)})
    (c,) = r.json()["commands"]
    assert c["ack"]["status"] == "accepted" and c["outcome"] is None
    r = w.client.get(
        "/api/v1/commands",
        params={"from": str(NOW - 1000), "to": str(NOW + 5000), "robot": "agv-2"},
    )
    assert r.json()["commands"] == []


def test_a_vda_vehicle_is_refused_goto_poi_saying_why_and_may_be_paused() -> None:
    w = World()
    vehicle = "acme:agv-7"  # robot_id_for("acme", "agv-7")
    w.store.append(
        [
            make_envelope(
                vehicle,
                NOW - 5_000,
                NOW - 5_000,
                PoseReported((1.0, 2.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
            )
        ]
    )
    w.client.post(
        "/api/v1/annotations",
        json={
            "id": "dock-1",
            "shape": "poi",
            "name": "dock",
            "kind": "station",
            "x": 3.5,
            "y": 4.0,
        },
        headers={"Authorization": f"Bearer {OPERATOR}"},
    )
    w.store.append([decode(v) for _, v in w.publisher.records[w.settings.topic_annotation_events]])
    r = w.send({"robotId": vehicle, "kind": "goto_poi", "poiId": "dock-1"})
    assert r.status_code == 422, r.text
    assert "VDA 5050 vehicle" in r.json()["detail"] and "master control" in r.json()["detail"]
    assert w.published() == []
    assert w.send({"robotId": vehicle, "kind": "pause"}).status_code == 202
