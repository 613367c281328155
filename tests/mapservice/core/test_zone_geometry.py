"""A zone's rings draw the area an operator meant, or are refused with the right reason,
in bounded time: generated simple polygons pass at every size, generated self-crossing
ones are refused at every size (above 500 vertices too), holes inside / outside / across
/ touching / nested, degenerate rings, coordinates far away or not numbers, and the cap
on vertices checked before any vertex is read."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from mapservice.core.annotations import AnnotationError, Zone, from_doc, to_doc, validate
from mapservice.core.zone_geometry import MAX_ZONE_VERTICES, ZoneGeometryError, check_zone_rings
from mapservice.core.zone_masks import Grid, mask_to_zones
from tests.geometry_kit import (
    bow_tie,
    convex_ring,
    crossing_ring,
    largest_allowed_zone_doc,
    parallel_comb_ring,
    star_ring,
    ui_clicked_ring,
)

SIZES = (3, 4, 17, 100, 499, 500, 501, 600, 2_000, MAX_ZONE_VERTICES)


def _zone(polygon, holes=()) -> Zone:
    return Zone("z", "keep_out", tuple(map(tuple, polygon)), tuple(tuple(h) for h in holes))


@pytest.mark.parametrize("n", SIZES)
def test_random_simple_polygons_of_every_size_are_valid(n) -> None:
    rng = random.Random(n)
    for _ in range(3):
        validate(_zone(star_ring(rng, n, cx=rng.uniform(-500, 500), cy=rng.uniform(-500, 500))))


@pytest.mark.parametrize("n", [s for s in SIZES if s >= 4])
def test_random_self_crossing_polygons_of_every_size_are_refused_as_crossing(n) -> None:
    """Points in convex position with a run of them reversed: two chords cross, always."""
    rng = random.Random(1000 + n)
    for _ in range(3):
        ring = crossing_ring(rng, n)
        with pytest.raises(AnnotationError, match=r"polygon crosses itself at \(.+\)"):
            validate(_zone(ring))
        hole = [(x / 20, y / 20) for x, y in crossing_ring(rng, min(n, MAX_ZONE_VERTICES - 4))]
        frame = [(-100.0, -100.0), (100.0, -100.0), (100.0, 100.0), (-100.0, 100.0)]
        with pytest.raises(AnnotationError, match=r"hole 0 crosses itself at"):
            validate(_zone(frame, [hole]))


def test_a_bow_tie_is_a_crossing_not_a_zone_without_area() -> None:
    for scale in (1e-3, 1.0, 1e5):
        with pytest.raises(AnnotationError, match="crosses itself") as info:
            validate(_zone(bow_tie(scale)))
        assert "no area" not in str(info.value)


def test_what_the_ui_draws_passes() -> None:
    """Rings as the UI's zone tool closes them (clicks in order round a point, the closing
    click dropped), and a zone dragged to another place (every vertex moved alike)."""
    rng = random.Random(7)
    for _ in range(200):
        ring = ui_clicked_ring(rng, rng.randrange(3, 40))
        validate(_zone(ring))
        dx, dy = rng.uniform(-50, 50), rng.uniform(-50, 50)
        validate(_zone([(x + dx, y + dy) for x, y in ring]))


SQUARE = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]


@pytest.mark.parametrize(
    ("hole", "reason"),
    [
        ([(2, 2), (4, 2), (4, 4), (2, 4)], None),  # inside
        ([(0, 0), (3, 1), (1, 3)], None),  # touches a corner of the polygon at one point
        ([(5, 0), (7, 2), (3, 2)], None),  # touches an edge of the polygon at one point
        ([(20, 20), (22, 20), (22, 22)], "hole 0 lies outside the polygon"),
        ([(-5, -5), (-1, -5), (-1, -1)], "hole 0 lies outside the polygon"),
        ([(8, 8), (12, 8), (12, 12), (8, 12)], "hole 0 crosses the polygon's edge"),
        ([(-1, 2), (11, 2), (11, 4), (-1, 4)], "hole 0 crosses the polygon's edge"),
        ([(-2, -2), (12, -2), (12, 12), (-2, 12)], "hole 0 lies outside the polygon"),  # around it
        ([(0, 2), (3, 2), (3, 4), (0, 4)], "cross or overlap"),  # shares part of an edge
        ([(0, 5), (5, 0), (10, 5), (5, 10)], "separate pieces"),  # cuts the zone in four
    ],
)
def test_a_hole_lies_inside_its_polygon(hole, reason) -> None:
    zone = _zone(SQUARE, [[(float(x), float(y)) for x, y in hole]])
    if reason is None:
        validate(zone)
        return
    with pytest.raises(AnnotationError, match=reason):
        validate(zone)


def test_holes_neither_overlap_nor_nest() -> None:
    a = [(1.0, 1.0), (5.0, 1.0), (5.0, 5.0), (1.0, 5.0)]
    overlapping = [(4.0, 4.0), (8.0, 4.0), (8.0, 8.0), (4.0, 8.0)]
    nested = [(2.0, 2.0), (3.0, 2.0), (3.0, 3.0)]
    touching = [(5.0, 5.0), (8.0, 5.0), (8.0, 8.0)]  # one shared corner: allowed
    validate(_zone(SQUARE, [a, touching]))
    with pytest.raises(AnnotationError, match="hole 0 and hole 1 cross or overlap"):
        validate(_zone(SQUARE, [a, overlapping]))
    with pytest.raises(AnnotationError, match="inside another hole"):
        validate(_zone(SQUARE, [a, nested]))


def test_random_holes_are_accepted_exactly_when_inside_and_apart() -> None:
    """Random small square holes in a 10 x 10 square: accepted exactly when each lies
    within the square and no two share a point (an independent oracle: boxes)."""
    rng = random.Random(11)
    for _ in range(300):
        boxes = []
        for _ in range(rng.randrange(1, 4)):
            x, y, s = rng.uniform(-3, 11), rng.uniform(-3, 11), rng.uniform(0.5, 3)
            boxes.append((x, y, x + s, y + s))
        holes = [[(a, b), (c, b), (c, d), (a, d)] for a, b, c, d in boxes]
        inside = all(0 < a and 0 < b and c < 10 and d < 10 for a, b, c, d in boxes)
        apart = all(
            p[2] < q[0] or q[2] < p[0] or p[3] < q[1] or q[3] < p[1]
            for i, p in enumerate(boxes)
            for q in boxes[i + 1 :]
        )
        zone = _zone(SQUARE, holes)
        if inside and apart:
            validate(zone)
        else:
            with pytest.raises(AnnotationError):
                validate(zone)


@pytest.mark.parametrize(
    ("ring", "reason"),
    [
        ([(0, 0), (1, 1)], "at least 3"),
        ([(0, 0), (1, 0), (2, 0)], "no area"),
        ([(0, 0), (1, 0), (2, 0), (3, 0), (1.5, 0)], "no area"),
        ([(0, 0), (1, 1), (2, 2), (3, 3)], "no area"),
        ([(0, 0), (1, 0), (1, 0), (0, 1)], "repeats vertex 1"),
        ([(0, 0), (1, 0), (0, 1), (0, 0)], "repeats vertex 3"),
        ([(0, 0), (1e-6, 0), (0, 1e-6)], "no area"),
        ([(0, 0), (2, 0), (2, 2), (1, 0), (0, 2)], "touches itself|crosses itself"),
    ],
)
def test_degenerate_rings_say_what_is_wrong(ring, reason) -> None:
    with pytest.raises(AnnotationError, match=reason):
        validate(_zone([(float(x), float(y)) for x, y in ring]))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e6 + 1, -1e300, 1e308])
def test_coordinates_far_away_or_not_numbers_are_refused(bad) -> None:
    for k in range(3):
        ring = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]
        ring[k][k % 2] = bad
        with pytest.raises(AnnotationError, match="finite number of metres"):
            validate(_zone(ring))
    far = [(1e6 - 10, 1e6 - 10), (1e6, 1e6 - 10), (1e6, 1e6)]
    validate(_zone(far))


def test_the_vertex_cap_counts_every_ring_and_is_checked_before_any_vertex() -> None:
    """The largest allowed zone passes; one vertex more is refused naming the cap, and a
    zone of a million vertices is refused from its lists' lengths alone."""
    doc = largest_allowed_zone_doc()
    assert len(doc["polygon"]) + sum(map(len, doc["holes"])) == MAX_ZONE_VERTICES
    from_doc(doc)
    over = {**doc, "holes": [*doc["holes"][:-1], [*doc["holes"][-1], doc["holes"][-1][0]]]}
    with pytest.raises(AnnotationError, match="MAX_ZONE_VERTICES"):
        from_doc(over)
    # A million vertices, not even valid ones: refused by the count, before any is read.
    huge = {**doc, "holes": [[[0, 0]] * 10_000] * 100}
    with pytest.raises(AnnotationError, match=f"at most {MAX_ZONE_VERTICES} in all"):
        from_doc(huge)
    with pytest.raises(ZoneGeometryError, match="MAX_ZONE_VERTICES"):
        check_zone_rings(tuple(SQUARE), [tuple(SQUARE)] * (MAX_ZONE_VERTICES // 4))


def test_zones_at_the_cap_are_judged_right() -> None:
    """At the cap's size a simple ring passes and a crossing one is refused as crossing
    (the pairwise check GEOS replaced gave up above 500 vertices). Their time while the
    probes are timed: tests/api/test_heavy_requests.py."""
    rng = random.Random(3)
    validate(from_doc(largest_allowed_zone_doc(), check=False))
    validate(_zone(star_ring(rng, MAX_ZONE_VERTICES)))
    with pytest.raises(AnnotationError, match="crosses itself"):
        validate(_zone(crossing_ring(rng, MAX_ZONE_VERTICES)))


def test_geoss_worst_valid_case_is_valid() -> None:
    validate(_zone(parallel_comb_ring(MAX_ZONE_VERTICES)))


def test_zones_traced_from_any_mask_are_valid_and_round_trip_their_json() -> None:
    grid = Grid(width=80, height=60, resolution=0.05, origin_x=-3.0, origin_y=2.0)
    for seed in range(8):
        mask = np.random.default_rng(seed).random((grid.height, grid.width)) < 0.15 + 0.1 * seed
        for zone in mask_to_zones(grid, mask, "m"):
            validate(zone)
            assert from_doc(to_doc(zone)) == zone


def test_convex_rings_of_every_size_are_valid() -> None:
    rng = random.Random(5)
    for n in SIZES:
        validate(_zone(convex_ring(rng, n)))
