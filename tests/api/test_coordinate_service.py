"""The 2019 coordinate service (appendix A.2, listing 17) over a MemoryStore."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.legacy_query import MAX_LIMIT
from mapservice.core.wire2019 import parse_timestamp
from mapservice.settings import Settings
from tests.fixtures.legacy import SpyStore

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
CLOCK_MS = NOW + 60_000
PATH = "/api/coordinate-service/robots"

# (robot, offset ms) of every pose.
POSES = [
    ("r1", 0),
    ("r1", 1000),
    ("r1", 2000),
    ("r1", 3000),
    ("r2", 0),
    ("r2", 1500),
    ("r3", -5000),
    ("r3", 2500),
    ("r4", 500),
    ("r4", 600),
    ("r4", 700),
    ("r4", 800),
]


@pytest.fixture
def store(ev) -> SpyStore:
    s = SpyStore()
    s.append(
        [
            ev.pose(
                robot,
                NOW + dt,
                x=dt / 1000,
                y=2.0,
                charging="sdf",
                loaded="dfs",
                path=((1.0, 2.0),) if robot == "r2" else None,
            )
            for robot, dt in POSES
        ]
    )
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(CLOCK_MS)), raise_server_exceptions=False
    )


def get(client, **params):
    r = client.get(PATH, params=params)
    assert r.status_code == 200, r.text
    return r.json()


def keys(body) -> list[tuple[str, int]]:
    return [(p["robotId"], parse_timestamp(p["timestamp"]) - NOW) for p in body]


def newest_first(poses):
    return sorted(poses, key=lambda p: (-p[1], p[0]))


def test_listing_17_shape_with_id(client) -> None:
    """Each entry has robotId, timestamp, pose.position/orientation, status.battery, loaded, _id."""
    [p] = get(client, robotId="r1", limit=1)
    assert p == {
        "robotId": "r1",
        "timestamp": "2026-11-21T10:00:03",
        "pose": {
            "position": {"x": 3.0, "y": 2.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        },
        "status": {"battery": {"battery_level": 80.0, "charging": "sdf"}, "loaded": "dfs"},
        "_id": "robotId:r1_2026-11-21T10:00:03",
    }
    [with_path] = get(client, robotId="r2", limit=1)
    assert with_path["plannedPath"] == [{"x": 1.0, "y": 2.0}]


def test_defaults_are_ten_newest_first(client) -> None:
    """No parameters: limit 10, newest first (ties by robot id)."""
    assert keys(get(client)) == newest_first(POSES)[:10]


def test_limit_and_skip(client) -> None:
    """limit cuts, skip pages on from there."""
    assert keys(get(client, limit=2)) == newest_first(POSES)[:2]
    assert keys(get(client, limit=3, skip=4)) == newest_first(POSES)[4:7]


@pytest.mark.parametrize(
    "param, value, expected",
    [
        ("robotId", "r3", lambda p: p[0] == "r3"),
        ("timestamp", "2026-11-21T10:00:00", lambda p: p[1] == 0),
        ("updatedSince", "2026-11-21T10:00:02", lambda p: p[1] >= 2000),
        ("updatedBefore", str(NOW + 600), lambda p: p[1] < 600),
    ],
)
def test_filters(client, param, value, expected) -> None:
    """robotId, timestamp, updatedSince (inclusive) and updatedBefore (exclusive) filter poses."""
    assert keys(get(client, limit=100, **{param: value})) == newest_first(
        [p for p in POSES if expected(p)]
    )


def test_sort(client) -> None:
    """sort=robotId:desc,timestamp:asc orders by the whitelisted fields."""
    assert keys(get(client, limit=100, sort="robotId:desc,timestamp:asc")) == sorted(
        POSES, key=lambda p: (-int(p[0][1:]), p[1])
    )
    assert keys(get(client, limit=100, sort="timestamp:asc")) == sorted(
        POSES, key=lambda p: (p[1], p[0])
    )


def test_latest_is_each_robots_newest_pose(client, store) -> None:
    """latest=true gives one pose per robot, its newest."""
    assert sorted(keys(get(client, latest="true"))) == [
        ("r1", 3000),
        ("r2", 1500),
        ("r3", 2500),
        ("r4", 800),
    ]
    assert store.called("robots_at") == [CLOCK_MS + 300_000]


def test_latest_with_updated_before_is_every_robot_at_t(client, store) -> None:
    """latest=true&updatedBefore=T is every robot's position just before T, from robots_at."""
    body = get(client, latest="true", updatedBefore="2026-11-21T10:00:01")
    assert keys(body) == [("r4", 800), ("r1", 0), ("r2", 0), ("r3", -5000)]
    assert store.called("robots_at") == [NOW + 999]
    assert store.called("list_poses") == []


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"sort": "row:asc"}, "'sort'"),
        ({"sort": "timestamp:desc;--"}, "'sort'"),
        ({"limit": str(MAX_LIMIT + 1)}, "'limit'"),
        ({"skip": "-3"}, "'skip'"),
        ({"latest": "perhaps"}, "'latest'"),
        ({"timestamp": "noon"}, "'timestamp'"),
        ({"updatedSince": "x"}, "'updatedSince'"),
        ({"robotId": "r" * 65}, "'robotId'"),
    ],
)
def test_malformed_parameters_are_400(client, params, fragment) -> None:
    """A malformed value is a 400 naming the parameter."""
    r = client.get(PATH, params=params)
    assert r.status_code == 400 and fragment in r.json()["detail"], r.text


def test_unknown_parameters_are_ignored(client) -> None:
    """Unknown parameters change nothing."""
    assert get(client, row="3", reduced="true", limit=3) == get(client, limit=3)
