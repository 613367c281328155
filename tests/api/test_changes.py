"""GET /api/v1/changes over a MemoryStore: newest first, area (rows/columns or metres),
robot, paging, uploads as one entry, and the 400s that say what to send instead."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.wire2019 import content_hash
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
HOUR = 3_600_000


def _px(i: int) -> bytes:
    return bytes([i]) * 10_000


@pytest.fixture
def client(ev) -> TestClient:
    s = MemoryStore()
    # meta_event: 4 x 5 chunks of 100 px at 5 cm, origin (-1.5, 2.0): chunk (r, c) spans
    # x in [-1.5 + 5c, -1.5 + 5(c+1)) and y in [2 + 5(3-r), 2 + 5(4-r)).
    s.append([ev.meta(NOW - 2 * HOUR)])
    s.append([ev.chunk("boot", NOW - HOUR + 100 * i, i // 5, i % 5, _px(i)) for i in range(20)])
    s.append(
        [
            ev.chunk("r1", NOW - 30 * 60_000, 0, 1, _px(100)),
            ev.chunk("r2", NOW - 20 * 60_000, 0, 1, _px(101)),
            ev.chunk("r1", NOW - 10 * 60_000, 3, 4, _px(102)),
        ]
    )
    return TestClient(
        create_app(Settings(), s, {}, ManualClock(NOW)), raise_server_exceptions=False
    )


def _get(client, **params):
    return client.get("/api/v1/changes", params={"from": NOW - 2 * HOUR, "to": NOW, **params})


def test_changes_newest_first_with_before_and_after_and_one_upload(client) -> None:
    r = _get(client)
    assert r.status_code == 200, r.text
    body = r.json()
    assert [(c["kind"], c["robot_id"], c["row"], c["column"]) for c in body["changes"]] == [
        ("change", "r1", 3, 4),
        ("change", "r2", 0, 1),
        ("change", "r1", 0, 1),
        ("upload", "boot", 0, 0),
    ]
    r2 = body["changes"][1]
    assert r2["ts_ms"] == NOW - 20 * 60_000
    assert (r2["previous_hash"], r2["content_hash"]) == (
        content_hash(_px(100)).hex(),
        content_hash(_px(101)).hex(),
    )
    assert body["changes"][2]["previous_hash"] == content_hash(_px(1)).hex()  # the upload's
    assert body["changes"][3]["chunks"] == 20 and body["next"] is None
    assert "20 or more chunk writes" in body["upload_rule"]


def test_changes_of_one_kind(client) -> None:
    uploads = _get(client, kind="upload").json()["changes"]
    assert [(c["kind"], c["robot_id"], c["chunks"]) for c in uploads] == [("upload", "boot", 20)]
    assert [c["kind"] for c in _get(client, kind="change").json()["changes"]] == ["change"] * 3
    r = _get(client, kind="floor")
    assert r.status_code in (400, 422) and "upload" in r.text


def test_changes_area_in_chunks_and_in_metres_agree(client) -> None:
    by_chunks = _get(client, row_min=0, row_max=0, col_min=1, col_max=1).json()["changes"]
    assert [(c["kind"], c["robot_id"]) for c in by_chunks] == [
        ("change", "r2"),
        ("change", "r1"),
        ("upload", "boot"),
    ]
    # Chunk (0, 1): x in [3.5, 8.5), y in [17, 22).
    by_metres = _get(client, x_min=4, x_max=8, y_min=18, y_max=21).json()["changes"]
    assert by_metres == by_chunks


def test_changes_robot_filter_and_paging(client) -> None:
    assert [c["robot_id"] for c in _get(client, robot="r1").json()["changes"]] == ["r1", "r1"]
    first = _get(client, limit=2).json()
    second = _get(client, limit=2, before=first["next"]).json()
    assert [c["robot_id"] for c in first["changes"] + second["changes"]] == [
        "r1",
        "r2",
        "r1",
        "boot",
    ]
    assert second["next"] is None


@pytest.mark.parametrize(
    "params, says",
    [
        ({"row_min": 0}, "needs all of row_min"),
        ({"x_min": 0}, "needs all of x_min"),
        (
            {
                "row_min": 0,
                "row_max": 0,
                "col_min": 0,
                "col_max": 0,
                "x_min": 1,
                "x_max": 2,
                "y_min": 1,
                "y_max": 2,
            },
            "not both",
        ),
        ({"row_min": 2, "row_max": 1, "col_min": 0, "col_max": 0}, "swap them"),
        ({"before": "nonsense"}, "not a page cursor"),
        ({"to": "yesterday"}, "neither ISO 8601"),
    ],
)
def test_changes_bad_input_says_what_to_send(client, params, says) -> None:
    r = _get(client, **params)
    assert r.status_code == 400 and says in r.json()["detail"], r.text


def test_a_window_with_too_many_writes_is_refused_with_what_to_do(client, monkeypatch) -> None:
    from mapservice.core import change_feed

    monkeypatch.setattr(change_feed, "MAX_WRITES", 10)
    r = _get(client)
    assert r.status_code == 422 and "choose a shorter span" in r.json()["detail"], r.text
    assert _get(client, **{"from": NOW - 15 * 60_000}).status_code == 200


def test_a_single_chunk_written_by_the_map_uploader_is_an_upload(ev) -> None:
    """The map uploader's writes are an upload however few: a one-chunk map upload is one
    `upload` entry, never a floor change."""
    s = MemoryStore()
    s.append([ev.meta(NOW - 2 * HOUR)])
    s.append(
        [
            ev.chunk("r1", NOW - HOUR, 0, 0, _px(1)),
            ev.chunk("map-upload", NOW - HOUR + 5_000, 0, 0, _px(2)),
        ]
    )
    client = TestClient(create_app(Settings(), s, {}, ManualClock(NOW)))
    body = _get(client).json()
    assert [(c["kind"], c["robot_id"], c["chunks"]) for c in body["changes"]] == [
        ("upload", "map-upload", 1),
        ("change", "r1", 1),
    ]


def test_a_weeks_uploads_are_served_though_the_week_is_too_busy_to_list(ev, monkeypatch) -> None:
    """The timeline's 7 d span: `kind=upload` answers with the week's uploads (newest first)
    where the whole feed of that week is refused, as a week of a large fleet is."""
    from mapservice.core import change_feed

    monkeypatch.setattr(change_feed, "MAX_WRITES", 100)
    s = MemoryStore()
    s.append([ev.meta(NOW - 7 * 24 * HOUR)])
    # A write a minute by each of three robots for the last 2 h: 360 writes, and two uploads.
    s.append(
        [
            ev.chunk(f"r{i % 3}", NOW - 2 * HOUR + 20_000 * i, i % 4, i % 5, _px(i % 7))
            for i in range(360)
        ]
    )
    s.append(
        [
            ev.chunk("map-upload", NOW - 6 * 24 * HOUR + 50 * i, i // 5, i % 5, _px(i))
            for i in range(20)
        ]
    )
    s.append(
        [ev.chunk("r1", NOW - HOUR + 30_500 + 500 * i, 3, i % 5, _px(50 + i)) for i in range(30)]
    )
    client = TestClient(create_app(Settings(), s, {}, ManualClock(NOW)))
    week = {"from": NOW - 7 * 24 * HOUR, "to": NOW}
    assert client.get("/api/v1/changes", params=week).status_code == 422
    r = client.get("/api/v1/changes", params={**week, "kind": "upload", "limit": 1000})
    assert r.status_code == 200, r.text
    assert [(c["robot_id"], c["chunks"], c["ts_ms"]) for c in r.json()["changes"]] == [
        ("r1", 30, NOW - HOUR + 30_500),
        ("map-upload", 20, NOW - 6 * 24 * HOUR),
    ]
