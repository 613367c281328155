"""The annotations' pure rules: the fold to an instant, the retention's pruning (the state
at and after the boundary unchanged), the JSON form and its validation."""

from __future__ import annotations

import random

import pytest

from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationEdit,
    AnnotationError,
    AnnotationRemoved,
    PointOfInterest,
    Zone,
    fold_annotations,
    from_doc,
    prune_before,
    to_doc,
)

POI = PointOfInterest("dock", "station", 1.0, 2.0, 0.5)
ZONE = Zone(
    "aisle",
    "speed_limit",
    ((0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0)),
    holes=(((1.0, 1.0), (2.0, 1.0), (2.0, 2.0)),),
    speed_limit=0.8,
    speed_unit="m/s",
)


def test_the_json_form_round_trips() -> None:
    for shape in (POI, ZONE):
        assert from_doc(to_doc(shape)) == shape


def test_a_hole_that_crosses_itself_is_refused() -> None:
    doc = to_doc(ZONE)
    doc["holes"] = [[[1, 1], [2, 2], [2, 1], [1, 1.5]]]
    with pytest.raises(AnnotationError, match="hole 0 crosses itself"):
        from_doc(doc)


def test_the_fold_applies_edits_in_time_order_and_keeps_the_creation() -> None:
    edits = [
        AnnotationEdit(30, "c", AnnotationRemoved("a", "op2")),
        AnnotationEdit(10, "a", AnnotationCreated("a", "op1", POI)),
        AnnotationEdit(20, "b", AnnotationChanged("a", "op2", ZONE)),
    ]
    assert fold_annotations(edits, 9) == {}
    assert fold_annotations(edits, 10)["a"].annotation == POI
    at20 = fold_annotations(edits, 20)["a"]
    assert (
        at20.annotation,
        at20.created_ms,
        at20.created_by,
        at20.changed_ms,
        at20.changed_by,
    ) == (ZONE, 10, "op1", 20, "op2")
    assert fold_annotations(edits, 30) == {}


def test_pruning_before_a_boundary_changes_no_state_from_the_boundary_on() -> None:
    """Random edits of a few annotations; after pruning at B the fold at every instant from
    B on is the same, and of the edits before B at most two per standing annotation stay."""
    rng = random.Random(5)
    edits = []
    for t in range(0, 2000, 7):
        aid = f"a{rng.randrange(6)}"
        kind = rng.choice(
            (AnnotationCreated, AnnotationChanged, AnnotationChanged, AnnotationRemoved)
        )
        event = (
            AnnotationRemoved(aid, "op")
            if kind is AnnotationRemoved
            else kind(aid, "op", PointOfInterest(f"p{t}", "note", float(t), 0.0))
        )
        edits.append(AnnotationEdit(t, f"e{t:05d}", event))
    for boundary in (0, 500, 1003, 1999):
        kept = prune_before(edits, boundary)
        for t in range(boundary, 2100, 13):
            assert fold_annotations(kept, t) == fold_annotations(edits, t), (boundary, t)
        standing = fold_annotations(edits, boundary)
        assert len([e for e in kept if e.ts_ms < boundary]) <= 2 * len(standing)
