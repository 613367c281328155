"""Masks into zones and back: any mask (islands, holes, islands in holes, pixels touching
only at a corner) traced into zones rasterises to exactly its pixels; the rasteriser agrees
with a point-at-a-time even-odd test on random polygons."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from mapservice.core import zone_masks
from mapservice.core.annotations import Zone, validate
from mapservice.core.zone_masks import Grid, keep_out_mask, mask_to_zones, rasterise

GRID = Grid(width=64, height=48, resolution=0.05, origin_x=-1.2, origin_y=3.4)


def _ring_mask() -> np.ndarray:
    m = np.zeros((GRID.height, GRID.width), dtype=bool)
    m[5:30, 5:40] = True
    m[10:25, 10:35] = False  # a hole
    m[14:20, 15:25] = True  # an island in the hole
    m[35, 50] = m[36, 51] = True  # two pixels touching only at a corner
    m[0, :] = True  # along the edge of the map
    return m


@pytest.mark.parametrize("seed", range(6))
def test_any_mask_traced_into_zones_rasterises_to_the_same_pixels(seed) -> None:
    rng = np.random.default_rng(seed)
    mask = _ring_mask() if seed == 0 else rng.random((GRID.height, GRID.width)) < (0.2 + 0.1 * seed)
    zones = mask_to_zones(GRID, mask, "imported")
    for zone in zones:
        validate(zone)
        assert zone.kind == "keep_out"
    assert ((keep_out_mask(GRID, zones) == 100) == mask).all()


def test_a_hole_belongs_to_its_zone() -> None:
    zones = mask_to_zones(GRID, _ring_mask(), "m")
    with_holes = [z for z in zones if z.holes]
    assert len(with_holes) == 1 and len(with_holes[0].holes) == 1
    assert len(zones) == 5  # the ring, the island, two corner pixels, the top row


def _inside(x: float, y: float, ring) -> bool:
    inside = False
    for i in range(len(ring)):
        (x0, y0), (x1, y1) = ring[i], ring[(i + 1) % len(ring)]
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


@pytest.mark.parametrize("seed", range(5))
def test_rasterise_agrees_with_a_point_at_a_time_test(seed) -> None:
    rng = random.Random(seed)
    n = rng.randint(3, 15)
    cx, cy = GRID.origin_x + rng.uniform(0, 3.2), GRID.origin_y + rng.uniform(0, 2.4)
    ring = [
        (cx + rng.uniform(0.1, 2) * math.cos(a), cy + rng.uniform(0.1, 2) * math.sin(a))
        for a in sorted(rng.uniform(0, 2 * math.pi) for _ in range(n))
    ]
    got = rasterise(GRID, [ring])
    for r in range(GRID.height):
        for c in range(GRID.width):
            x = GRID.origin_x + (c + 0.5) * GRID.resolution
            y = GRID.origin_y + (GRID.height - r - 0.5) * GRID.resolution
            assert got[r, c] == _inside(x, y, ring), (r, c)


@pytest.mark.parametrize("batch", [1, 7, 1000])
def test_rasterising_in_batches_of_crossings_gives_the_same_pixels(batch, monkeypatch) -> None:
    """Any batch size of (edge, row) crossings, even one at a time, paints the same pixels
    as all at once: random rings, some with many vertices, some reaching off the grid."""
    rng = random.Random(batch)
    rings = [
        [
            (
                GRID.origin_x + 1.6 + rng.uniform(0.1, 2.5) * math.cos(a),
                GRID.origin_y + 1.2 + rng.uniform(0.1, 2.5) * math.sin(a),
            )
            for a in sorted(rng.uniform(0, 2 * math.pi) for _ in range(rng.randint(3, 300)))
        ]
        for _ in range(6)
    ]
    whole = [rasterise(GRID, [ring]) for ring in rings]
    monkeypatch.setattr(zone_masks, "_CROSSINGS_AT_ONCE", batch)
    assert all((rasterise(GRID, [ring]) == want).all() for ring, want in zip(rings, whole))


def _zone(ring) -> Zone:
    return Zone("z", "keep_out", tuple(ring))


def test_a_zone_too_costly_to_rasterise_is_refused_naming_the_cap() -> None:
    """The cells of its box on the grid and its edges' crossings of pixel rows, each
    capped, counted before any rasterising; a zone at the caps passes."""
    side = math.isqrt(zone_masks.MAX_ZONE_MASK_CELLS)
    grid = Grid(width=side + 10, height=side + 10, resolution=0.05, origin_x=0.0, origin_y=0.0)
    extent = side * grid.resolution
    zone_masks.check_raster_cost(grid, _zone([(0.0, 0.0), (extent, 0.0), (extent, extent)]))
    bigger = extent + grid.resolution
    with pytest.raises(zone_masks.ZoneMaskError, match="MAX_ZONE_MASK_CELLS"):
        zone_masks.check_raster_cost(grid, _zone([(0.0, 0.0), (bigger, 0.0), (bigger, bigger)]))
    # A comb of teeth, each two edges crossing every row: over the crossings' cap.
    teeth = zone_masks.MAX_ZONE_ROW_CROSSINGS // (2 * 1000) + 1
    comb = [(0.0, 0.0)]
    for k in range(teeth):
        comb += [(k * 0.2 + 0.05, 50.0), (k * 0.2 + 0.1, 50.0), (k * 0.2 + 0.15, 0.01)]
    comb.append((teeth * 0.2 + 0.2, 0.0))
    assert sum(zone_masks.raster_cost(grid, [comb])) < zone_masks.MAX_ZONE_MASK_CELLS
    with pytest.raises(zone_masks.ZoneMaskError, match="MAX_ZONE_ROW_CROSSINGS"):
        zone_masks.check_raster_cost(grid, _zone(comb))


def test_the_outline_of_a_mask_is_counted_and_capped_before_tracing() -> None:
    """boundary_edges equals the traced rings' perimeters (an independent count); a mask
    at MAX_TRACED_EDGES passes, one pixel more is refused naming the cap."""
    for seed in range(6):
        mask = np.random.default_rng(seed).random((GRID.height, GRID.width)) < 0.1 + 0.15 * seed
        perimeter = sum(
            abs(a[0] - b[0]) + abs(a[1] - b[1])
            for ring in zone_masks.trace_rings(mask)
            for a, b in zip(ring, ring[1:] + ring[:1])
        )
        assert zone_masks.boundary_edges(mask) == perimeter
    pixels = zone_masks.MAX_TRACED_EDGES // 4  # isolated pixels: 4 edges each
    mask = np.zeros((2 * (pixels // 500 + 1), 1000), dtype=bool)
    mask[::2, ::2].flat[:pixels] = True
    zone_masks.check_traceable(mask)
    mask[::2, ::2].flat[pixels] = True
    with pytest.raises(zone_masks.ZoneMaskError, match="MAX_TRACED_EDGES"):
        zone_masks.check_traceable(mask)
