"""The live views' pure rules: which write is live, the 2019 advertisement, robot status."""

from __future__ import annotations

import base64
import io
import zlib

from PIL import Image

from mapservice.core.liveview import (
    advertisement,
    apply_chunks,
    apply_poses,
    chunk_id_2019,
    clock_skew_ms,
    is_online,
    online_robots,
    skew_flagged,
)
from tests.conftest import NOW_MS, chunk_event, pose_event

PIXELS = bytes(i % 251 for i in range(100 * 100))


def test_newer_write_replaces_and_is_returned_once_per_chunk() -> None:
    """Newer writes replace the live version; per chunk only the final one is returned."""
    view: dict = {}
    e1, e2, e3 = (
        chunk_event("a", NOW_MS, 1, 1),
        chunk_event("b", NOW_MS + 5, 1, 1),
        chunk_event("a", NOW_MS, 0, 0),
    )
    assert apply_chunks(view, [e1, e2, e3]) == [e2, e3]
    assert view[(1, 1)].robot_id == "b" and view[(1, 1)].ts_ms == NOW_MS + 5


def test_older_and_redelivered_writes_do_not_change_the_view() -> None:
    """An older write, or the live one again, changes nothing and is not advertised."""
    view: dict = {}
    live = chunk_event("a", NOW_MS, 1, 1)
    apply_chunks(view, [live])
    assert apply_chunks(view, [chunk_event("b", NOW_MS - 1, 1, 1, bytes(10_000)), live]) == []
    assert view[(1, 1)].robot_id == "a"


def test_equal_times_go_to_the_greater_robot_id() -> None:
    """Two robots at one instant: the greater robot id is live (as in the map at T)."""
    view: dict = {}
    apply_chunks(view, [chunk_event("b", NOW_MS, 1, 1)])
    assert apply_chunks(view, [chunk_event("a", NOW_MS, 1, 1)]) == []
    assert len(apply_chunks(view, [chunk_event("c", NOW_MS, 1, 1)])) == 1


def test_advertisement_has_the_2019_shape_and_resolvable_urls() -> None:
    """The payload is listing 15 field for field; chunkUrl is the 2019 chunk-by-id route."""
    e = chunk_event("lkjlkj", 1_545_348_873_000, 3, 2, PIXELS)
    ad = advertisement(e, "http://maps.example:8080/")
    assert list(ad) == [
        "row",
        "column",
        "robotId",
        "chunk",
        "png",
        "timestamp",
        "id",
        "chunkUrl",
        "pngUrl",
    ]
    assert ad["id"] == "row:3_column:2_2018-12-20T23:34:33"
    assert ad["timestamp"] == "2018-12-20T23:34:33"
    assert (
        ad["chunkUrl"]
        == "http://maps.example:8080/api/chunk-service/chunks/id/row:3_column:2_2018-12-20T23:34:33"
    )
    assert ad["pngUrl"] == ad["chunkUrl"] + "/png"
    assert (ad["row"], ad["column"], ad["robotId"]) == (3, 2, "lkjlkj")
    assert zlib.decompress(base64.b64decode(ad["chunk"])) == PIXELS
    image = Image.open(io.BytesIO(base64.b64decode(ad["png"])))
    assert image.size == (100, 100) and image.tobytes() == PIXELS


def test_advertisements_render_each_content_once_and_never_mix_contents(monkeypatch) -> None:
    """A content advertised again reuses its encoding; other contents get their own."""
    import mapservice.core.liveview as liveview

    rendered = []
    real_png = liveview.png
    monkeypatch.setattr(liveview, "png", lambda image: rendered.append(1) or real_png(image))
    other = bytes([254]) * 10_000
    ads = [
        advertisement(chunk_event(r, 1_545_348_873_000 + i, i, 0, px), "http://m/")
        for i, (r, px) in enumerate([("a", PIXELS), ("b", other), ("c", PIXELS), ("d", other)])
    ]
    assert [zlib.decompress(base64.b64decode(ad["chunk"])) for ad in ads] == [
        PIXELS,
        other,
        PIXELS,
        other,
    ]
    assert [Image.open(io.BytesIO(base64.b64decode(ad["png"]))).tobytes() for ad in ads] == [
        PIXELS,
        other,
        PIXELS,
        other,
    ]
    assert len(rendered) <= 2


def test_chunk_id_keeps_milliseconds() -> None:
    """A write with milliseconds keeps them in its id (as format_timestamp does)."""
    assert chunk_id_2019(0, 1, 1_545_348_873_250) == "row:0_column:1_2018-12-20T23:34:33.250"


def test_robot_view_keeps_latest_pose_and_last_seen() -> None:
    """A late pose does not replace the latest one but still counts as being heard from."""
    view: dict = {}
    assert apply_poses(view, [pose_event("r1", NOW_MS, x=1.0)]) == ["r1"]
    late = pose_event("r1", NOW_MS - 60_000, x=9.0, receive_lag_ms=70_000)
    assert apply_poses(view, [late]) == []
    state = view["r1"]
    assert state.position[0] == 1.0 and state.ts_ms == NOW_MS
    assert state.last_seen_ms == NOW_MS + 10_000
    assert online_robots(view, NOW_MS + 20_000, 10.0) == {"r1"}
    assert online_robots(view, NOW_MS + 20_001, 10.0) == set()


def test_skew_and_presence_thresholds() -> None:
    """Skew is receive minus event time, flagged beyond the threshold; online up to the limit."""
    assert clock_skew_ms(1_000, 7_000) == -6_000
    assert skew_flagged(-6_000, 5.0) and not skew_flagged(5_000, 5.0)
    assert is_online(10_000, 10.0) and not is_online(10_001, 10.0)
