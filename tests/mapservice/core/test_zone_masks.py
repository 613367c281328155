"""Masks into zones and back: any mask (islands, holes, islands in holes, pixels touching
only at a corner) traced into zones rasterises to exactly its pixels; the rasteriser agrees
with a point-at-a-time even-odd test on random polygons."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from mapservice.core.annotations import validate
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
