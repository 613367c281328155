"""Robots learn that the zones changed: the processors' live views advertise every stored
create, change and removal of a zone on the zone advertisement topic (next to the chunk
advertisements), with where to fetch the masks as of that edit; points of interest are not
advertised; a removal of a zone the views learnt from the history is advertised too."""

from __future__ import annotations

import asyncio

import pytest

from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationRemoved,
    PointOfInterest,
    Zone,
)
from mapservice.core.events import make_envelope
from mapservice.processors.sink import HistorySink
from mapservice.processors.views import LiveViews
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import NOW_MS
from tests.processors.history_consumer_kit import live_views

ZONE = Zone("aisle 3", "keep_out", ((0.0, 0.0), (2.0, 0.0), (2.0, 1.0)))
POI = PointOfInterest("dock", "station", 1.0, 1.0)


class TopicAdvertiser:
    def __init__(self) -> None:
        self.sent: list[tuple[str, dict]] = []

    def start(self) -> None:
        pass

    def publish(self, payload: dict) -> bool:
        return self.publish_to("chunks", payload)

    def publish_to(self, topic: str, payload: dict) -> bool:
        self.sent.append((topic, payload))
        return True

    def stop(self) -> None:
        pass


@pytest.fixture
def sink():
    s = HistorySink(MemoryStore())
    yield s
    s.thread.close()


def _edit(t: int, event):
    return make_envelope("operator:ab12", t, t, event)


def _stored(views: LiveViews, sink: HistorySink, *events) -> None:
    sink.writer.append(list(events))
    asyncio.run(views.on_stored(list(events)))
    views.flush()


def test_zone_edits_are_advertised_on_the_zone_topic_and_points_of_interest_are_not(sink) -> None:
    ads = TopicAdvertiser()
    settings = Settings(
        public_base_url="http://api:8080", zone_advertisement_topic="iot/zones/advertisement"
    )
    views = live_views(settings, sink.writer, ads, sink.thread, now_ms=lambda: NOW_MS)
    views.load()
    _stored(
        views,
        sink,
        _edit(NOW_MS, AnnotationCreated("z1", "operator:ab12", ZONE)),
        _edit(NOW_MS, AnnotationCreated("p1", "operator:ab12", POI)),
    )
    _stored(views, sink, _edit(NOW_MS + 1000, AnnotationChanged("p1", "operator:ab12", POI)))
    _stored(views, sink, _edit(NOW_MS + 2000, AnnotationRemoved("p1", "operator:ab12")))
    assert [(t, p["annotationId"], p["change"]) for t, p in ads.sent] == [
        ("iot/zones/advertisement", "z1", "created")
    ]
    _, ad = ads.sent[0]
    assert ad["by"] == "operator:ab12" and ad["ts_ms"] == NOW_MS
    assert (
        ad["keepOutMaskUrl"]
        == f"http://api:8080/api/v1/costmap-filters/keepout/mask.yaml?at={NOW_MS}"
    )
    assert ad["speedFilterInfoUrl"].startswith(
        "http://api:8080/api/v1/costmap-filters/speed/filter-info.yaml"
    )
    # A point of interest turned into a zone is a zone change; its removal too.
    _stored(views, sink, _edit(NOW_MS + 3000, AnnotationCreated("p2", "operator:ab12", POI)))
    _stored(views, sink, _edit(NOW_MS + 4000, AnnotationChanged("p2", "operator:ab12", ZONE)))
    _stored(views, sink, _edit(NOW_MS + 5000, AnnotationRemoved("p2", "operator:ab12")))
    assert [(p["annotationId"], p["change"]) for _, p in ads.sent[1:]] == [
        ("p2", "changed"),
        ("p2", "removed"),
    ]


def test_a_zone_known_from_the_history_is_advertised_when_removed(sink) -> None:
    """After a restart the views learn the standing zones from the store: removing one is
    advertised although this process never saw it created."""
    sink.writer.append([_edit(NOW_MS, AnnotationCreated("z1", "operator:ab12", ZONE))])
    ads = TopicAdvertiser()
    views = live_views(Settings(), sink.writer, ads, sink.thread, now_ms=lambda: NOW_MS + 60_000)
    views.load()
    _stored(views, sink, _edit(NOW_MS + 60_000, AnnotationRemoved("z1", "operator:ab12")))
    assert [(t, p["change"]) for t, p in ads.sent] == [("iot/zones/advertisement", "removed")]


def test_a_pose_inside_a_keep_out_zone_is_a_zone_violation(sink) -> None:
    """After a keep-out zone is stored, a robot's pose on one of its pixels is a violation
    (stored, listed by the API); poses outside it, poses before it existed, and poses in a
    speed zone are not; once the zone is removed, none."""
    from fastapi.testclient import TestClient

    from mapservice.adapters.clock import ManualClock
    from mapservice.api.app import create_app
    from tests.conftest import meta_event, pose_event

    sink.writer.append([meta_event(NOW_MS - 10_000)])  # 500 x 400 px at 0.05 m from (-1.5, 2.0)
    views = live_views(
        Settings(), sink.writer, TopicAdvertiser(), sink.thread, now_ms=lambda: NOW_MS + 100_000
    )
    views.load()
    keep_out = Zone("pit", "keep_out", ((0.0, 3.0), (2.0, 3.0), (2.0, 5.0), (0.0, 5.0)))
    slow = Zone(
        "slow",
        "speed_limit",
        ((5.0, 3.0), (7.0, 3.0), (7.0, 5.0)),
        speed_limit=50.0,
        speed_unit="percent",
    )
    _stored(
        views,
        sink,
        _edit(NOW_MS, AnnotationCreated("pit", "operator:ab12", keep_out)),
        _edit(NOW_MS, AnnotationCreated("slow", "operator:ab12", slow)),
    )
    _stored(
        views,
        sink,
        pose_event("amr-1", NOW_MS + 1000, x=1.0, y=4.0),  # inside
        pose_event("amr-2", NOW_MS + 1000, x=3.0, y=4.0),  # outside
        pose_event("amr-3", NOW_MS + 1000, x=6.5, y=3.5),  # in the speed zone
        pose_event("amr-4", NOW_MS - 5000, x=1.0, y=4.0),
    )  # before the zone existed
    _stored(views, sink, _edit(NOW_MS + 2000, AnnotationRemoved("pit", "operator:ab12")))
    _stored(views, sink, pose_event("amr-1", NOW_MS + 3000, x=1.0, y=4.0))
    found = sink.writer.zone_violations(NOW_MS - 60_000, NOW_MS + 60_000)
    assert [(v.robot_id, v.annotation_id, v.ts_ms) for v in found] == [
        ("amr-1", "pit", NOW_MS + 1000)
    ]
    client = TestClient(create_app(Settings(), sink.writer, {}, ManualClock(NOW_MS + 100_000)))
    body = client.get(
        "/api/v1/zone-violations", params={"from": str(NOW_MS - 60_000), "to": str(NOW_MS + 60_000)}
    ).json()
    assert [(v["robotId"], v["zoneId"], v["x"], v["y"]) for v in body["violations"]] == [
        ("amr-1", "pit", 1.0, 4.0)
    ]
