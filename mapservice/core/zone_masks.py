"""Zones as nav2 costmap filter masks, and masks back into zones.

A mask is an occupancy grid aligned with the map (same origin, resolution and size):
nav2's map_server serves it, a CostmapFilterInfo names how to read it (type 0 keep-out,
1 speed in % of the maximum, 2 speed in m/s; filter value = base + multiplier x mask value).

The rule, exact and documented so anyone can check a mask: a pixel belongs to a zone when
its centre lies inside the zone's rings under the even-odd rule, a centre on a horizontal
edge's row counting as above it (half-open rows), one on a vertical edge's column as
right of it (a ray cast to the right). A zone imported from a mask has its edges on pixel
edges, so no centre lies on one and import then export gives back the same pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import msgspec
import numpy as np
import shapely

from mapservice.core.annotations import Ring, Zone, signed_area

KEEP_OUT, SPEED_PERCENT, SPEED_MPS = 0, 1, 2  # CostmapFilterInfo.type
MASK_FREE, MASK_KEEP_OUT = 0, 100  # OccupancyGrid values


class Grid(msgspec.Struct, frozen=True):
    """The map's raster: width x height pixels of `resolution` metres, the lower-left
    pixel's corner at `origin` (x, y) in the map frame (the map's YAML)."""

    width: int
    height: int
    resolution: float
    origin_x: float
    origin_y: float


class FilterInfo(msgspec.Struct, frozen=True):
    """The CostmapFilterInfo parameters that read a mask (nav2 costmap_filter_info_server)."""

    type: int
    base: float
    multiplier: float


def _edges_in_pixels(grid: Grid, rings: Sequence[Ring]) -> np.ndarray:
    """Every edge of every ring as (x0, y0, x1, y1) in pixel units, y down from the top."""
    parts = []
    for ring in rings:
        pts = np.asarray(ring, dtype=np.float64)
        px = (pts[:, 0] - grid.origin_x) / grid.resolution
        py = grid.height - (pts[:, 1] - grid.origin_y) / grid.resolution
        parts.append(np.stack([px, py, np.roll(px, -1), np.roll(py, -1)], axis=1))
    return np.concatenate(parts) if parts else np.zeros((0, 4))


# What one zone may cost to rasterise: the cells of its box on the map's grid (a whole
# 8,000 x 8,000 map), and the crossings of its edges with the pixel rows (a ring crosses
# each row a few times; a zigzag of many vertices across many rows is refused).
MAX_ZONE_MASK_CELLS = 64_000_000
MAX_ZONE_ROW_CROSSINGS = 4_000_000
_CROSSINGS_AT_ONCE = 1 << 20  # rasterised in batches: memory bounded whatever the zone


class ZoneMaskError(ValueError):
    """A zone too costly to rasterise on this map, or a mask too intricate to trace into
    zones; the message says how large and the cap."""


def _window(grid: Grid, edges: np.ndarray) -> tuple[int, int, int, int]:
    """(first row, end row, first column, end column) of the edges' box, clipped to the grid."""
    xs, ys = edges[:, [0, 2]], edges[:, [1, 3]]
    r0 = int(min(max(math.floor(ys.min()), 0), grid.height))
    r1 = int(min(max(math.ceil(ys.max()), 0), grid.height))
    c0 = int(min(max(math.floor(xs.min()), 0), grid.width))
    c1 = int(min(max(math.ceil(xs.max()), 0), grid.width))
    return r0, r1, c0, c1


def _rows_crossed(edges: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """Per edge, the first window row whose centre line r + 0.5 it crosses (lying in
    [min y, max y)) and how many rows it crosses (0 for horizontal edges)."""
    y0, y1 = edges[:, 1], edges[:, 3]
    lo, hi = np.minimum(y0, y1), np.maximum(y0, y1)
    first = np.maximum(np.ceil(lo - 0.5), r0)
    last = np.minimum(np.ceil(hi - 0.5) - 1, r1 - 1)
    count = np.where(y0 != y1, np.maximum(last - first + 1, 0), 0)
    return first.astype(np.int64), count.astype(np.int64)


def raster_cost(grid: Grid, rings: Sequence[Ring]) -> tuple[int, int]:
    """(cells of the rings' box on the grid, crossings of their edges with pixel rows):
    what rasterising them costs, computed in one linear pass before any rasterising."""
    edges = _edges_in_pixels(grid, rings)
    if not len(edges):
        return 0, 0
    r0, r1, c0, c1 = _window(grid, edges)
    return (r1 - r0) * (c1 - c0), int(_rows_crossed(edges, r0, r1)[1].sum())


def check_raster_cost(grid: Grid, zone: Zone) -> None:
    """ZoneMaskError when the zone costs more than the caps to rasterise on this map (its
    masks are drawn for every nav2 mask, violation check and export)."""
    cells, crossings = raster_cost(grid, (zone.polygon, *zone.holes))
    if cells > MAX_ZONE_MASK_CELLS:
        raise ZoneMaskError(
            f"the zone spans {cells} cells of the map's {grid.resolution:g} m grid; at most "
            f"{MAX_ZONE_MASK_CELLS} (MAX_ZONE_MASK_CELLS): split it into smaller zones"
        )
    if crossings > MAX_ZONE_ROW_CROSSINGS:
        raise ZoneMaskError(
            f"the zone's edges cross the map's pixel rows {crossings} times; at most "
            f"{MAX_ZONE_ROW_CROSSINGS} (MAX_ZONE_ROW_CROSSINGS): simplify its outline "
            "or split it into smaller zones"
        )


def rasterise_window(grid: Grid, rings: Sequence[Ring]) -> tuple[int, int, np.ndarray]:
    """(first row, first column, boolean window): the pixels whose centre is inside the
    rings (even-odd), within the rings' bounding box clipped to the grid. Each
    non-horizontal edge toggles, on every pixel row whose centre line it crosses, the
    pixels left of the crossing; the parity of the toggles is inside (kept modulo 256 in
    bytes: the parity is all that counts)."""
    edges = _edges_in_pixels(grid, rings)
    if not len(edges):
        return 0, 0, np.zeros((0, 0), dtype=bool)
    r0, r1, c0, c1 = _window(grid, edges)
    toggles = np.zeros((r1 - r0, c1 - c0 + 1), dtype=np.uint8)
    first, crossed = _rows_crossed(edges, r0, r1)
    ends = np.cumsum(crossed)
    start = 0
    while start < len(edges):
        # The next edges up to _CROSSINGS_AT_ONCE crossings (at least one edge).
        stop = max(
            int(np.searchsorted(ends, ends[start] - crossed[start] + _CROSSINGS_AT_ONCE, "right")),
            start + 1,
        )
        _toggle(toggles, edges[start:stop], first[start:stop], crossed[start:stop], r0, c0, c1)
        start = stop
    np.cumsum(toggles[:, : c1 - c0], axis=1, dtype=np.uint8, out=toggles[:, : c1 - c0])
    return r0, c0, (toggles[:, : c1 - c0] & 1).astype(bool)


def _toggle(
    toggles: np.ndarray,
    edges: np.ndarray,
    first: np.ndarray,
    crossed: np.ndarray,
    r0: int,
    c0: int,
    c1: int,
) -> None:
    """Every (edge, row) crossing of these edges at once: each edge's index repeated once
    per row it crosses, its crossing's x, and the toggles it makes."""
    which = np.repeat(np.arange(len(edges)), crossed)
    rows = np.repeat(first, crossed) + (
        np.arange(len(which)) - np.repeat(np.cumsum(crossed) - crossed, crossed)
    )
    x0, y0, x1, y1 = (edges[which, k] for k in range(4))
    xi = x0 + (rows + 0.5 - y0) * (x1 - x0) / (y1 - y0)
    # Centres c + 0.5 < xi: columns up to ceil(xi - 0.5) - 1. Columns left of the
    # window toggle nothing inside it, but the parity they carry does: counted at c0.
    n = np.clip(np.ceil(xi - 0.5), c0, c1).astype(np.int64) - c0
    toggles[:, 0] += np.bincount(rows - r0, minlength=toggles.shape[0]).astype(np.uint8)
    np.subtract.at(toggles, (rows - r0, n), np.uint8(1))


def rasterise(grid: Grid, rings: Sequence[Ring]) -> np.ndarray:
    """Boolean (height, width), row 0 at the top: the pixels whose centre is inside the
    rings (even-odd rule, pixel centres; the module's docstring has the exact rule)."""
    out = np.zeros((grid.height, grid.width), dtype=bool)
    r0, c0, window = rasterise_window(grid, rings)
    out[r0 : r0 + window.shape[0], c0 : c0 + window.shape[1]] = window
    return out


def _paint(mask: np.ndarray, grid: Grid, zone: Zone) -> tuple[slice, slice, np.ndarray]:
    r0, c0, window = rasterise_window(grid, (zone.polygon, *zone.holes))
    return slice(r0, r0 + window.shape[0]), slice(c0, c0 + window.shape[1]), window


def zone_pixels(grid: Grid, zone: Zone) -> np.ndarray:
    return rasterise(grid, (zone.polygon, *zone.holes))


def keep_out_mask(grid: Grid, zones: Sequence[Zone]) -> np.ndarray:
    """OccupancyGrid values (uint8): 100 inside any keep-out zone, 0 elsewhere."""
    mask = np.zeros((grid.height, grid.width), dtype=bool)
    for zone in zones:
        if zone.kind == "keep_out":
            rows, cols, window = _paint(mask, grid, zone)
            mask[rows, cols] |= window
    return np.where(mask, MASK_KEEP_OUT, MASK_FREE).astype(np.uint8)


def keep_out_labels(grid: Grid, zones: Sequence[tuple[str, Zone]]) -> tuple[np.ndarray, list[str]]:
    """Per pixel 0 (free) or 1 + the index into the returned ids of a keep-out zone that
    covers it (where zones overlap, the later one): which zone a pose lies in, by the same
    pixel rule as the keep-out mask."""
    labels = np.zeros((grid.height, grid.width), dtype=np.int32)
    ids: list[str] = []
    for annotation_id, zone in zones:
        if zone.kind != "keep_out":
            continue
        ids.append(annotation_id)
        r0, c0, window = rasterise_window(grid, (zone.polygon, *zone.holes))
        region = labels[r0 : r0 + window.shape[0], c0 : c0 + window.shape[1]]
        region[window] = len(ids)
    return labels, ids


def pixel_of(grid: Grid, x: float, y: float) -> tuple[int, int] | None:
    """(row, column) of the pixel holding map point (x, y), row 0 at the top; None outside."""
    c = math.floor((x - grid.origin_x) / grid.resolution)
    r = grid.height - 1 - math.floor((y - grid.origin_y) / grid.resolution)
    if 0 <= r < grid.height and 0 <= c < grid.width:
        return r, c
    return None


def speed_filter_info(zones: Sequence[Zone], unit: str) -> FilterInfo:
    """Percent: the mask value is the percentage (1..100). m/s: the mask value times
    `multiplier` = the limit, the multiplier the fastest limit / 100, so that limit is
    exact and the others within half a multiplier (rounded down: never faster)."""
    if unit == "percent":
        return FilterInfo(SPEED_PERCENT, 0.0, 1.0)
    limits = [z.speed_limit for z in zones if z.kind == "speed_limit" and z.speed_unit == unit]
    top = max((v for v in limits if v is not None), default=1.0)
    return FilterInfo(SPEED_MPS, 0.0, top / 100.0)


def speed_mask(grid: Grid, zones: Sequence[Zone], unit: str) -> tuple[np.ndarray, FilterInfo]:
    """OccupancyGrid values (uint8, 0 = no limit) of the speed zones in `unit` (overlapping
    zones: the lowest limit wins) and the FilterInfo that turns them back into limits."""
    info = speed_filter_info(zones, unit)
    mask = np.zeros((grid.height, grid.width), dtype=np.uint8)
    for zone in zones:
        if zone.kind != "speed_limit" or zone.speed_unit != unit or zone.speed_limit is None:
            continue
        value = int(
            min(max(math.floor((zone.speed_limit - info.base) / info.multiplier + 1e-9), 1), 100)
        )
        rows, cols, inside = _paint(mask, grid, zone)
        region = mask[rows, cols]
        region[inside] = np.where(
            (region[inside] == 0) | (region[inside] > value), value, region[inside]
        )
    return mask, info


# --- masks into zones ------------------------------------------------------------------

# Directions in pixel-corner space (x right, y down): right, down, left, up.
_STEPS = ((1, 0), (0, 1), (-1, 0), (0, -1))


MAX_TRACED_EDGES = 200_000  # pixel edges between masked and free a mask may have to be traced


def boundary_edges(mask: np.ndarray) -> int:
    """How many pixel edges separate masked from free pixels (the map's border counting as
    free): the work of tracing the mask, and a bound on its zones' vertices (4 per zone at
    least, so a quarter of it bounds their number)."""
    padded = np.pad(mask.astype(bool), 1)
    return int((padded[1:, :] != padded[:-1, :]).sum() + (padded[:, 1:] != padded[:, :-1]).sum())


def check_traceable(mask: np.ndarray) -> None:
    """ZoneMaskError for a mask whose outline is longer than MAX_TRACED_EDGES pixel edges
    (a checkerboard's is 2 per pixel): counted in one pass before any tracing."""
    edges = boundary_edges(mask)
    if edges > MAX_TRACED_EDGES:
        raise ZoneMaskError(
            f"the mask's keep-out areas have {edges} pixel edges of outline; at most "
            f"{MAX_TRACED_EDGES} are traced into zones (MAX_TRACED_EDGES): a mask of a few "
            "solid areas has far fewer (smooth or clean it before importing)"
        )


def trace_rings(mask: np.ndarray) -> list[list[tuple[int, int]]]:
    """The boundary of the True pixels as closed rings of pixel corners (x, y down), each
    running clockwise on screen around the inside (holes the other way), collinear
    vertices merged. Where two pixels touch only at a corner the ring turns towards the
    inside, so rings never cross (they may touch at that corner)."""
    h, w = mask.shape
    padded = np.zeros((h + 2, w + 2), dtype=bool)
    padded[1:-1, 1:-1] = mask
    inside = padded[1:-1, 1:-1]
    out: dict[tuple[int, int], list[int]] = {}  # corner -> directions of unused edges

    def add(cells: np.ndarray, dx: int, dy: int, direction: int) -> None:
        for r, c in zip(*np.nonzero(cells)):
            out.setdefault((int(c) + dx, int(r) + dy), []).append(direction)

    add(inside & ~padded[:-2, 1:-1], 0, 0, 0)  # top edge, going right
    add(inside & ~padded[1:-1, 2:], 1, 0, 1)  # right edge, going down
    add(inside & ~padded[2:, 1:-1], 1, 1, 2)  # bottom edge, going left
    add(inside & ~padded[1:-1, :-2], 0, 1, 3)  # left edge, going up
    rings = []
    for start in sorted(out):
        while out.get(start):
            direction = out[start].pop()
            ring = [start]
            x, y = start
            while True:
                x, y = x + _STEPS[direction][0], y + _STEPS[direction][1]
                choices = out.get((x, y))
                if not choices:
                    break  # back at the start: its edges are all used
                # Prefer a right turn (towards the inside), then straight, then left.
                for turn in (1, 0, 3):
                    nxt = (direction + turn) % 4
                    if nxt in choices:
                        break
                else:
                    nxt = choices[0]
                choices.remove(nxt)
                if nxt != direction:
                    ring.append((x, y))
                direction = nxt
            if ring[0] == ring[-1]:
                ring.pop()
            # The start may lie mid-edge of the ring: drop it when collinear.
            if len(ring) > 2 and _collinear(ring[-1], ring[0], ring[1]):
                ring.pop(0)
            rings.extend(_loops(ring))
    return rings


def _loops(ring: list[tuple[int, int]]) -> list[list[tuple[int, int]]]:
    """A ring that passes a corner twice (pixels meeting there only diagonally) as the
    simple loops it is made of, cut at that corner: the same edges, so the same pixels by
    the even-odd rule, and each loop a simple ring (a valid polygon's ring, GEOS's rule)."""
    loops: list[list[tuple[int, int]]] = []
    path: list[tuple[int, int]] = []
    at: dict[tuple[int, int], int] = {}
    for corner in ring:
        seen = at.get(corner)
        if seen is None:
            at[corner] = len(path)
            path.append(corner)
            continue
        loops.append(path[seen:])
        for dropped in path[seen + 1 :]:
            del at[dropped]
        del path[seen + 1 :]
    loops.append(path)
    return loops


def _collinear(a: tuple[int, int], b: tuple[int, int], c: tuple[int, int]) -> bool:
    return bool((b[0] - a[0]) * (c[1] - a[1]) == (b[1] - a[1]) * (c[0] - a[0]))


def mask_to_zones(grid: Grid, mask: np.ndarray, name: str, kind: str = "keep_out") -> list[Zone]:
    """The True pixels of `mask` (height, width; row 0 at the top) as zones: one per
    outer boundary with the holes inside it, vertices on pixel edges in map metres."""

    def metres(ring: list[tuple[int, int]]) -> Ring:
        return tuple(
            (
                grid.origin_x + x * grid.resolution,
                grid.origin_y + (grid.height - y) * grid.resolution,
            )
            for x, y in ring
        )

    outers: list[Ring] = []
    holes: list[Ring] = []
    for ring in trace_rings(mask):
        m = metres(ring)
        # Outer rings run clockwise (negative area in the map frame), holes the other way.
        (outers if signed_area(m) < 0 else holes).append(m)
    owned: list[list[Ring]] = [[] for _ in outers]
    probes = []
    for hole in holes:
        # A point just inside a masked pixel next to the hole's first edge lies in the
        # component around the hole: the smallest outer ring containing it owns the hole.
        (ax, ay), (bx, by) = hole[0], hole[1]
        mx, my = (ax + bx) / 2, (ay + by) / 2
        # Every ring has the masked pixels on its right-hand side.
        dx, dy = bx - ax, by - ay
        length = math.hypot(dx, dy)
        probes.append(
            (mx + dy / length * grid.resolution / 4, my - dx / length * grid.resolution / 4)
        )
    if holes and outers:
        # GEOS's index: each probe meets only the outers whose box holds it, not all of them.
        areas = np.array([-signed_area(o) for o in outers])
        tree = shapely.STRtree(shapely.polygons([shapely.linearrings(o) for o in outers]))
        probe, outer = tree.query(shapely.points(probes), predicate="within")
        best: dict[int, int] = {}
        for p, o in zip(probe.tolist(), outer.tolist(), strict=True):
            if p not in best or areas[o] < areas[best[p]]:
                best[p] = o
        for p, o in sorted(best.items()):
            owned[o].append(holes[p])
    return [
        Zone(
            name=f"{name} {k + 1}" if len(outers) > 1 else name,
            kind=kind,
            polygon=outer,
            holes=tuple(owned[k]),
        )
        for k, outer in enumerate(outers)
    ]
