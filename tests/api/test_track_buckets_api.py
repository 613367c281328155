"""GET /api/v1/robots/{id}/track-buckets over a MemoryStore: the plots' per-bucket read.

A figure does not depend on the zoom: over generated windows and bucket counts, the
buckets' distances add up to a plain fold of the raw poses (GET /api/v1/poses) and speed is
distance over the steps' time; the size is round and chosen by the span; bad input is a 400
that says what to change, before the store is asked."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.api.routers.tracks import MAX_TRACK_BUCKETS
from mapservice.core.track_buckets import BUCKET_SIZES_MS
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
HOUR = 3_600_000
DAY = 24 * HOUR
START = NOW - 3 * HOUR


@pytest.fixture(scope="module")
def store() -> MemoryStore:
    """A robot driving a random walk, a pose a second for two hours with a silent half hour
    in between, battery falling; another robot elsewhere."""
    from tests.conftest import pose_event

    rng = np.random.default_rng(11)
    times = [START + i * 1000 for i in range(3600)] + [
        START + 90 * 60_000 + i * 1000 for i in range(3600)
    ]
    xy = np.cumsum(rng.normal(0, 0.4, (len(times), 2)), axis=0)
    s = MemoryStore()
    s.append(
        [
            pose_event("walker", t, x=float(x), y=float(y), battery_level=90 - i / 200)
            for i, (t, (x, y)) in enumerate(zip(times, xy, strict=True))
        ]
        + [pose_event("other", START + i * 5000, x=50.0 + i) for i in range(100)]
    )
    return s


@pytest.fixture(scope="module")
def client(store) -> TestClient:
    settings = Settings(api_rate_limit="", api_allowed_hosts=["testserver"])
    app = create_app(settings, store, {}, ManualClock(NOW))
    return TestClient(app, raise_server_exceptions=False)


def _buckets(client, f, t, n, robot="walker"):
    r = client.get(
        f"/api/v1/robots/{robot}/track-buckets", params={"from": f, "to": t, "buckets": n}
    )
    assert r.status_code == 200, r.text
    return r.json()


def _raw_distance(client, f, t, robot="walker") -> float:
    poses = client.get(
        "/api/v1/poses", params={"from": f, "to": t, "robotId": robot, "limit": 100_000}
    ).json()
    poses.sort(key=lambda p: p["ts_ms"])
    return sum(math.dist(a["position"][:2], b["position"][:2]) for a, b in zip(poses, poses[1:]))


@pytest.mark.parametrize("seed", range(6))
def test_the_distance_of_a_window_is_the_raw_folds_at_every_bucket_count(client, seed) -> None:
    rng = np.random.default_rng(seed)
    f = START - int(rng.integers(0, HOUR))
    t = START + int(rng.integers(HOUR, 4 * HOUR))
    raw = _raw_distance(client, f, t)
    assert raw > 100
    for n in sorted(
        {
            2,
            3,
            int(rng.integers(4, 50)),
            int(rng.integers(50, MAX_TRACK_BUCKETS)),
            MAX_TRACK_BUCKETS,
        }
    ):
        body = _buckets(client, f, t, n)
        size = body["bucket_ms"]
        assert size in BUCKET_SIZES_MS or size % DAY == 0
        assert (t - 1) // size - f // size + 1 <= n
        assert body["distance_m"] == pytest.approx(raw, rel=1e-9)
        assert sum(b["distance_m"] for b in body["buckets"]) == pytest.approx(raw, rel=1e-9)
        for b in body["buckets"]:
            assert b["start_ms"] % size == 0 and b["start_ms"] <= b["first_ms"]
            assert b["last_ms"] < b["start_ms"] + size
            if b["step_ms"]:
                assert b["speed_mps"] == pytest.approx(b["distance_m"] / (b["step_ms"] / 1000))
            else:
                assert b["speed_mps"] is None
            assert b["battery_min"] <= b["battery_mean"] <= b["battery_max"]


def test_a_day_reads_the_same_in_hours_and_in_a_week(client) -> None:
    """The day's distance from its 24 hours' reads, from the day's and from a week's buckets
    (whole hours: a day is whole buckets) differ only by the steps across the reads' edges."""
    day = START - START % DAY
    whole = _buckets(client, day, day + DAY, 300)["distance_m"]
    hours = sum(
        _buckets(client, day + h * HOUR, day + (h + 1) * HOUR, 360)["distance_m"] for h in range(24)
    )
    week = _buckets(client, day + DAY - 7 * DAY + HOUR, day + DAY, 200)
    in_day = sum(b["distance_m"] for b in week["buckets"] if day <= b["start_ms"] < day + DAY)
    assert whole == pytest.approx(_raw_distance(client, day, day + DAY), rel=1e-9)
    assert hours == pytest.approx(whole, rel=0.01) and in_day == pytest.approx(whole, rel=1e-3)


def test_an_unknown_robot_is_404_and_a_quiet_window_is_empty(client) -> None:
    r = client.get("/api/v1/robots/ghost/track-buckets", params={"from": START, "to": NOW})
    assert r.status_code == 404 and "'ghost'" in r.json()["detail"]
    body = _buckets(client, NOW - 20 * 60_000, NOW, 10)  # the walker stopped 30 min ago
    assert body["buckets"] == [] and body["distance_m"] == 0


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"buckets": 1}, "between 2 and"),
        ({"buckets": MAX_TRACK_BUCKETS + 1}, "between 2 and"),
        ({"from": NOW - 8 * DAY}, "split it"),
        ({"from": NOW - 7 * DAY - HOUR, "to": NOW - 6 * DAY}, "retention"),
        ({"from": NOW, "to": NOW - 1}, "swap"),
        ({"from": "yesterday"}, "neither ISO 8601"),
    ],
)
def test_bad_parameters_are_400_before_the_store_is_asked(store, client, params, fragment) -> None:
    asked = []
    original = store.track_buckets
    store.track_buckets = lambda *a: asked.append(a) or original(*a)
    try:
        r = client.get(
            "/api/v1/robots/walker/track-buckets", params={"from": START, "to": NOW, **params}
        )
    finally:
        del store.track_buckets
    assert r.status_code == 400, r.text
    assert fragment in r.json()["detail"] and asked == []
