"""Generators of zones and mask images for tests: simple and self-crossing rings of any
size, what the UI's zone tool draws, the largest zone the API accepts, and PNGs that are
small on the wire but huge or intricate once decoded (a decompression bomb, a
checkerboard) - the heavy requests a harness sends while it watches the probes."""

from __future__ import annotations

import io
import math
import random
import struct
import zlib

import numpy as np
from PIL import Image

from mapservice.core.zone_geometry import MAX_ZONE_VERTICES

Point = tuple[float, float]


def _angles(rng: random.Random, n: int) -> list[float]:
    """n increasing angles, each in its own n-th of the turn: no gap reaches half a turn."""
    return [(k + rng.uniform(0.3, 0.7)) * 2 * math.pi / n for k in range(n)]


def star_ring(
    rng: random.Random, n: int, cx: float = 0.0, cy: float = 0.0, radius: float = 50.0
) -> list[Point]:
    """A random simple ring of n vertices: star-shaped round (cx, cy), radii at random."""
    return [
        (cx + r * math.cos(a), cy + r * math.sin(a))
        for a, r in ((a, rng.uniform(radius / 2, radius)) for a in _angles(rng, n))
    ]


def convex_ring(rng: random.Random, n: int, radius: float = 50.0) -> list[Point]:
    """n random points on a circle, in order: a convex ring."""
    return [(radius * math.cos(a), radius * math.sin(a)) for a in _angles(rng, n)]


def crossing_ring(rng: random.Random, n: int, radius: float = 50.0) -> list[Point]:
    """A convex ring (n >= 4) with a run of 2 to n - 2 vertices reversed: for points in
    convex position, the two edges that now join the run to the rest always cross."""
    ring = convex_ring(rng, n, radius)
    length = rng.randint(2, n - 2)
    start = rng.randrange(n)
    ring = ring[start:] + ring[:start]  # the run first, then at least two others
    return ring[:length][::-1] + ring[length:]


def parallel_comb_ring(vertices: int) -> list[Point]:
    """A valid ring that is GEOS's worst case: teeth of long parallel diagonal edges a
    millimetre apart, every edge's box overlapping every other's (no index helps), so
    checking it costs nearer n² than n log n. `vertices` is rounded down to 4k + 2."""
    teeth = (vertices - 2) // 4
    ring: list[Point] = []
    for k in range(teeth):
        x = k * 0.001
        ring += [(x, 0.0), (x + 50.0, 50.0), (x + 50.0005, 50.0), (x + 0.0005, 0.0)]
    return [*ring, (teeth * 0.001 + 0.01, -1.0), (-0.01, -1.0)]


def bow_tie(scale: float = 1.0) -> list[Point]:
    """Two triangles meeting where two edges cross: zero signed area, not zero area."""
    return [(0.0, 0.0), (scale, scale), (scale, 0.0), (0.0, scale)]


def ui_clicked_ring(rng: random.Random, clicks: int, tolerance: float = 0.05) -> list[Point]:
    """What the UI's zone tool sends: clicks round a point on a centimetre grid, the
    double-click's repeated closing point and near-duplicates dropped (its closeRing)."""
    raw = [(round(x, 2), round(y, 2)) for x, y in star_ring(rng, clicks, radius=20.0)]
    raw += [raw[-1], raw[0]]
    out: list[Point] = []
    for p in raw:
        if not out or math.hypot(p[0] - out[-1][0], p[1] - out[-1][1]) > tolerance:
            out.append(p)
    while len(out) > 1 and math.hypot(out[0][0] - out[-1][0], out[0][1] - out[-1][1]) <= tolerance:
        out.pop()
    return out


def _circle(cx: float, cy: float, r: float, n: int, clockwise: bool = False) -> list[list[float]]:
    step = -2 * math.pi / n if clockwise else 2 * math.pi / n
    return [[cx + r * math.cos(k * step), cy + r * math.sin(k * step)] for k in range(n)]


def largest_allowed_zone_doc(
    radius_m: float = 60.0, cx: float = 0.0, cy: float = 0.0, holes: int = 100
) -> dict:
    """The API body of a valid keep-out zone with exactly MAX_ZONE_VERTICES vertices: an
    outer circle and `holes` (the API's most) small circles in a square grid inside it.
    Scale `radius_m` to the map's resolution to also approach the rasterising cap
    (mapservice.core.zone_masks.MAX_ZONE_RASTER_CELLS: about (2 x radius / resolution)²)."""
    side = math.ceil(math.sqrt(holes))
    per_hole = (MAX_ZONE_VERTICES - 200) // holes
    outer = MAX_ZONE_VERTICES - per_hole * holes
    spacing = 1.2 * radius_m / side
    rings = []
    for k in range(holes):
        i, j = divmod(k, side)
        hx = cx + (i - (side - 1) / 2) * spacing
        hy = cy + (j - (side - 1) / 2) * spacing
        rings.append(_circle(hx, hy, spacing / 3, per_hole, clockwise=True))
    return {
        "shape": "zone",
        "name": "largest allowed",
        "kind": "keep_out",
        "polygon": _circle(cx, cy, radius_m, outer),
        "holes": rings,
    }


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bomb(width: int, height: int, truncate: bool = False) -> bytes:
    """A valid 8-bit grey PNG of width x height zeros, compressed row by row (never whole in
    memory): 12,000 x 14,000 is 168 MB of pixels in about 0.2 MB. `truncate` cuts its
    image data in half (a decoder then fails after having inflated that much)."""
    packer = zlib.compressobj(9)
    row = b"\0" * (width + 1)  # filter byte 0, then the pixels
    parts = [packer.compress(row) for _ in range(height)]
    data = b"".join(parts) + packer.flush()
    if truncate:
        data = data[: len(data) // 2]
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", data)
        + (b"" if truncate else _chunk(b"IEND", b""))
    )


def png_header_only(width: int, height: int) -> bytes:
    """A PNG's signature and header for width x height (up to 2³¹ - 1 each) and no image
    data: what a decoder reads before it decides to allocate."""
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IEND", b"")


def checkerboard(width: int, height: int, cell: int = 1) -> np.ndarray:
    """Keep-out (True) on alternate cells of `cell` pixels: every cell its own area."""
    rows, cols = np.indices((height, width)) // cell
    return ((rows + cols) % 2).astype(bool)


def mask_png(keep_out: np.ndarray) -> bytes:
    """A nav2 trinary keep-out mask as PNG: 0 (occupied) where True, 254 (free) elsewhere."""
    out = io.BytesIO()
    Image.fromarray(np.where(keep_out, 0, 254).astype(np.uint8)).save(out, format="PNG")
    return out.getvalue()


def mask_yaml(resolution: float, origin: tuple[float, float]) -> str:
    return (
        f"image: mask.png\nmode: trinary\nresolution: {resolution}\n"
        f"origin: [{origin[0]}, {origin[1]}, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
