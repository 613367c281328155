"""The replay reads over a MemoryStore: events windows, timeline density, robot tracks."""

from __future__ import annotations

import math

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.api.routers import events as events_router
from mapservice.core.events import PoseReported, make_envelope
from mapservice.core.ports import ConflictRow
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z, a whole minute
MIN = 60_000
HOUR = 3_600_000
DAY = 86_400_000


def _heading(robot: str, t_ms: int, x: float, angle: float, battery: float = 50.0):
    """A pose facing `angle` radians (a rotation about z)."""
    payload = PoseReported(
        position=(x, 2.0, 0.0),
        orientation=(0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)),
        battery_level=battery,
    )
    return make_envelope(robot, t_ms, t_ms + 10, payload)


@pytest.fixture
def store(ev) -> MemoryStore:
    s = MemoryStore()
    s.append([ev.pose(r, NOW + i * 1000, x=float(i)) for i in range(120) for r in ("r1", "r2")])
    s.append(
        [
            ev.chunk("r1", NOW + 500, 1, 1),
            ev.chunk("r2", NOW + 500, 0, 2),
            ev.chunk("r1", NOW + 61_000, 1, 1, bytes([7]) * 10_000),
            ev.chunk("r2", NOW - 1, 0, 0),
        ]
    )
    s.append(
        [
            _heading("r3", NOW + 5 * MIN, 1.0, math.pi / 2, 40.0),
            _heading("r3", NOW + 5 * MIN + 1000, 2.0, -math.pi / 4, 39.5),
        ]
    )
    s.append_conflicts([ConflictRow(1, 1, NOW + 61_000, "r2", NOW + 60_500, "r1")])
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(NOW + HOUR)), raise_server_exceptions=False
    )


def _get(client, path, f, t, **params):
    return client.get(path, params={"from": f, "to": t, **params})


# --- events ------------------------------------------------------------------------------


def test_events_window_has_every_chunk_and_pose_in_order(client) -> None:
    """[from, to) holds every chunk change in event-time order and every pose (step 0)."""
    r = _get(client, "/api/v1/events", NOW, NOW + 2000)
    assert r.status_code == 200, r.text
    body = r.json()
    assert (body["from_ms"], body["to_ms"], body["step_ms"], body["truncated"]) == (
        NOW,
        NOW + 2000,
        0,
        False,
    )
    assert [(c["row"], c["column"], c["robotId"], c["ts_ms"]) for c in body["chunks"]] == [
        (0, 2, "r2", NOW + 500),
        (1, 1, "r1", NOW + 500),
    ]
    assert body["chunks"][0]["timestamp"] == "2026-11-21T10:00:00.500"
    assert len(body["chunks"][0]["content_hash"]) == 32
    assert [(p["robotId"], p["ts_ms"] - NOW) for p in body["poses"]] == [
        ("r1", 0),
        ("r2", 0),
        ("r1", 1000),
        ("r2", 1000),
    ]
    pose = body["poses"][2]
    assert pose["position"] == [1.0, 2.0, 0.0] and pose["orientation"] == [0.0, 0.0, 0.0, 1.0]
    assert pose["receive_time_ms"] == NOW + 1040 and pose["path"] is None


def test_events_downsampled_keeps_all_chunks_and_one_pose_per_robot_per_step(client) -> None:
    """step_ms > 0 thins the poses to each robot's first per step; chunk changes stay all."""
    body = _get(client, "/api/v1/events", NOW, NOW + 2 * MIN, step_ms=MIN).json()
    assert [(p["robotId"], p["ts_ms"] - NOW) for p in body["poses"]] == [
        ("r1", 0),
        ("r2", 0),
        ("r1", MIN),
        ("r2", MIN),
    ]
    assert len(body["chunks"]) == 3 and body["step_ms"] == MIN


def test_events_cut_at_a_cap_are_complete_up_to_the_returned_to(client, monkeypatch) -> None:
    """Past the pose cap: truncated, to_ms moves back, and [from, to_ms) is complete."""
    monkeypatch.setattr(events_router, "MAX_POSES", 5)
    body = _get(client, "/api/v1/events", NOW, NOW + 10_000).json()
    assert body["truncated"] is True
    assert body["to_ms"] == NOW + 2000
    assert [(p["robotId"], p["ts_ms"] - NOW) for p in body["poses"]] == [
        ("r1", 0),
        ("r2", 0),
        ("r1", 1000),
        ("r2", 1000),
    ]
    assert [c["ts_ms"] for c in body["chunks"]] == [NOW + 500, NOW + 500]


def test_events_chunk_step_keeps_each_chunks_last_change_per_bucket(client, ev, store) -> None:
    """chunk_step_ms > 0: per chunk and absolute bucket only its winner; poses unchanged."""
    store.append([ev.chunk("r2", NOW + 30_000, 1, 1, bytes([3]) * 10_000)])
    every = _get(client, "/api/v1/events", NOW, NOW + 2 * MIN).json()
    body = _get(client, "/api/v1/events", NOW, NOW + 2 * MIN, chunk_step_ms=MIN).json()
    assert [(c["row"], c["column"], c["robotId"], c["ts_ms"] - NOW) for c in body["chunks"]] == [
        (0, 2, "r2", 500),
        (1, 1, "r2", 30_000),
        (1, 1, "r1", 61_000),
    ]
    assert len(every["chunks"]) == 4 and every["chunk_step_ms"] == 0
    assert body["chunk_step_ms"] == MIN and body["poses"] == every["poses"]


@pytest.mark.parametrize("value, status", [("-1", 400), ("1.5", 422), ("soon", 422)])
def test_events_bad_chunk_step_is_refused_naming_the_parameter(client, value, status) -> None:
    """A negative chunk_step_ms is a 400 as a negative step_ms is; a non-integer a 422; both name it."""
    r = _get(client, "/api/v1/events", NOW, NOW + 1000, chunk_step_ms=value)
    assert r.status_code == status, r.text
    assert "chunk_step_ms" in r.text


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"from": NOW + 1000, "to": NOW}, "swap"),
        ({"from": NOW, "to": NOW + DAY + 1}, "split"),
        ({"from": NOW, "to": NOW + 1000, "step_ms": -1}, "negative"),
        ({"from": NOW - 8 * DAY, "to": NOW - 8 * DAY + 1000}, "retention"),
        ({"from": "last tuesday", "to": NOW}, "ISO 8601"),
    ],
)
def test_events_bad_parameters_are_400_saying_what_to_fix(client, params, fragment) -> None:
    """Swapped, too long, pre-retention or unparseable windows and negative steps are 400s."""
    r = client.get("/api/v1/events", params=params)
    assert r.status_code == 400, r.text
    assert fragment in r.json()["detail"]


def test_events_window_just_inside_the_retention_is_fine(client) -> None:
    """A window starting at now minus the retention (as clients compute it) is accepted."""
    now = NOW + HOUR
    assert _get(client, "/api/v1/events", now - 7 * DAY, now - 7 * DAY + 1000).status_code == 200


# --- timeline ----------------------------------------------------------------------------


def test_timeline_counts_per_bucket(client) -> None:
    """N buckets of equal length; chunk changes, conflicts and active robots per bucket."""
    r = _get(client, "/api/v1/timeline", NOW, NOW + 6 * MIN, buckets=3)
    assert r.status_code == 200, r.text
    body = r.json()
    assert (body["from_ms"], body["to_ms"], body["bucket_ms"]) == (NOW, NOW + 6 * MIN, 2 * MIN)
    assert body["buckets"] == [
        {"start_ms": NOW, "chunk_changes": 3, "conflicts": 1, "robots_active": 2},
        {"start_ms": NOW + 2 * MIN, "chunk_changes": 0, "conflicts": 0, "robots_active": 0},
        {"start_ms": NOW + 4 * MIN, "chunk_changes": 0, "conflicts": 0, "robots_active": 1},
    ]


def test_timeline_uneven_span_rounds_the_bucket_up(client) -> None:
    """A span that N does not divide gets whole-ms buckets covering it, never more than N."""
    body = _get(client, "/api/v1/timeline", NOW, NOW + 1000, buckets=3).json()
    assert body["bucket_ms"] == 334
    assert [b["start_ms"] - NOW for b in body["buckets"]] == [0, 334, 668]
    assert [b["robots_active"] for b in body["buckets"]] == [2, 0, 0]


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"buckets": 0}, "between 1 and 2000"),
        ({"buckets": 2001}, "between 1 and 2000"),
        ({"buckets": 10**9}, "between 1 and 2000"),
        ({"from": NOW - 7 * DAY, "to": NOW + 2 * HOUR}, "longer than"),
        ({"from": NOW + 1, "to": NOW}, "swap"),
    ],
)
def test_timeline_bad_parameters_are_400(client, params, fragment) -> None:
    """Absurd bucket counts, spans beyond the retention and swapped windows are 400s."""
    r = client.get("/api/v1/timeline", params={"from": NOW, "to": NOW + HOUR, **params})
    assert r.status_code == 400, r.text
    assert fragment in r.json()["detail"]


# --- tracks ------------------------------------------------------------------------------


def test_track_points_carry_position_yaw_and_battery(client) -> None:
    """A track lists the robot's poses in the window with yaw from the quaternion."""
    r = _get(client, "/api/v1/robots/r3/track", NOW, NOW + HOUR)
    assert r.status_code == 200, r.text
    body = r.json()
    assert (body["robotId"], body["from_ms"], body["to_ms"]) == ("r3", NOW, NOW + HOUR)
    first, second = body["points"]
    assert (first["ts_ms"], first["x"], first["y"], first["battery_level"]) == (
        NOW + 5 * MIN,
        1.0,
        2.0,
        40.0,
    )
    assert first["yaw"] == pytest.approx(math.pi / 2, abs=1e-6)
    assert second["yaw"] == pytest.approx(-math.pi / 4, abs=1e-6)


def test_track_with_step_has_one_point_per_step(client) -> None:
    """step_ms > 0 keeps the robot's first pose in each step."""
    body = _get(client, "/api/v1/robots/r1/track", NOW, NOW + 2 * MIN, step_ms=MIN).json()
    assert [p["ts_ms"] - NOW for p in body["points"]] == [0, MIN]
    assert [p["x"] for p in body["points"]] == [0.0, 60.0]


def test_track_of_a_known_robot_in_an_empty_window_is_empty(client) -> None:
    """A robot that reported, asked for a window where it did not, gets 200 and no points."""
    r = _get(client, "/api/v1/robots/r3/track", NOW, NOW + MIN)
    assert r.status_code == 200 and r.json()["points"] == []


def test_track_of_an_unknown_robot_is_404_with_a_hint(client) -> None:
    """A robot that never reported is a 404 naming it and where robots are listed."""
    r = _get(client, "/api/v1/robots/ghost/track", NOW, NOW + HOUR)
    assert r.status_code == 404
    assert "'ghost'" in r.json()["detail"] and "/api/v1/robots" in r.json()["detail"]


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"step_ms": -5}, "negative"),
        ({"to": NOW + DAY + 1}, "split"),
        ({"to": NOW + 2 * DAY, "step_ms": 1}, "use step_ms >= 1728"),
        ({"from": NOW + 1, "to": NOW}, "swap"),
    ],
)
def test_track_bad_parameters_are_400(client, params, fragment) -> None:
    """Negative steps, too many points and swapped windows are 400s saying what to change."""
    r = client.get("/api/v1/robots/r1/track", params={"from": NOW, "to": NOW + HOUR, **params})
    assert r.status_code == 400, r.text
    assert fragment in r.json()["detail"]
