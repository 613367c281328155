"""Both stores keep operators' annotation edits and zone violations alike: the annotations
at each instant, the edits of a window, violations by time (deduplicated on their identity)."""

from __future__ import annotations

from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationRemoved,
    PointOfInterest,
    Zone,
    ZoneViolation,
)
from mapservice.core.events import make_envelope
from tests.conftest import NOW_MS

ZONE = Zone(
    "pit",
    "keep_out",
    ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)),
    holes=(((0.5, 0.5), (1.0, 0.5), (1.0, 1.0)),),
    note="forklifts",
)
POI = PointOfInterest("charger 2", "charger", 3.25, -1.5, 3.14)


def _edit(t: int, event):
    return make_envelope("operator:x", t, t, event)


def test_annotations_and_their_edits_at_any_instant(store) -> None:
    edits = [
        _edit(NOW_MS, AnnotationCreated("z", "operator:x", ZONE)),
        _edit(NOW_MS + 10, AnnotationCreated("p", "operator:y", POI)),
        _edit(
            NOW_MS + 20,
            AnnotationChanged("z", "operator:y", Zone("pit 2", "keep_out", ZONE.polygon)),
        ),
        _edit(NOW_MS + 30, AnnotationRemoved("p", "operator:x")),
    ]
    store.append(edits)
    store.append(edits[:2])  # a redelivery changes nothing
    assert store.annotations_at(NOW_MS - 1) == []
    at10 = {a.annotation_id: a for a in store.annotations_at(NOW_MS + 10)}
    assert at10["z"].annotation == ZONE and at10["p"].annotation == POI
    at20 = {a.annotation_id: a for a in store.annotations_at(NOW_MS + 20)}
    assert at20["z"].annotation.name == "pit 2" and at20["z"].created_ms == NOW_MS
    assert at20["z"].changed_by == "operator:y"
    assert [a.annotation_id for a in store.annotations_at(NOW_MS + 30)] == ["z"]
    window = store.annotation_edits(NOW_MS + 5, NOW_MS + 30)
    assert [(e.ts_ms, e.event.annotation_id) for e in window] == [
        (NOW_MS + 10, "p"),
        (NOW_MS + 20, "z"),
    ]


def test_zone_violations_by_time(store) -> None:
    rows = [
        ZoneViolation(NOW_MS + 5, "amr-2", "z", 1.5, 1.25),
        ZoneViolation(NOW_MS, "amr-1", "z", 1.0, 1.0),
    ]
    store.append_zone_violations(rows)
    store.append_zone_violations(rows[:1])
    assert store.zone_violations(NOW_MS, NOW_MS + 6) == sorted(rows, key=lambda v: v.ts_ms)
    assert store.zone_violations(NOW_MS + 1, NOW_MS + 5) == []
