"""Whether a zone's rings draw the area an operator meant, decided by GEOS (shapely).

A zone is a polygon with holes read by the even-odd rule (mapservice/core/zone_masks.py).
That rule gives every set of rings some area, so a ring that crosses itself, a hole outside
its polygon or one across its edge would silently mean something else than was drawn (a
hole outside adds keep-out area). The rings are therefore held to the OGC rules for a valid
polygon, which GEOS checks in O(n log n): each ring simple (no crossing, no touching
itself), every hole inside the polygon and no two holes overlapping or nested. A hole may
touch the polygon or another hole at single points, as the rings traced from a mask do.

Every check is bounded: the total number of vertices is capped before anything else is
looked at, the per-vertex checks are linear, and a valid zone costs one pass of GEOS.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np
import shapely

Point = tuple[float, float]
Ring = tuple[Point, ...]

# All rings of one zone together. GEOS's validity costs O(n log n) on ordinary outlines
# but nearer O(n²) on the worst valid ones (thousands of long parallel edges, all their
# boxes overlapping): about a second at this cap on this project's machines. The largest
# zone traced from the shared warehouse keep-out mask has 714 vertices.
MAX_ZONE_VERTICES = 5_000
MAX_COORDINATE_M = 1_000_000.0  # a kilometre-sized factory is 1,000 m; beyond is a typo
# Twice the area below this (m²) is no area at all: a ring whose vertices nearly lie on a line.
_NO_AREA_M2 = 1e-9
_REASON = re.compile(r"^(?P<kind>[^\[]+)\[(?P<x>\S+) (?P<y>\S+)\]")


class ZoneGeometryError(ValueError):
    """Rings that are not a zone anyone meant; the message says what to change."""


def signed_area(ring: Ring) -> float:
    """Shoelace area in m²: positive when the ring runs counter-clockwise."""
    n = len(ring)
    return 0.5 * sum(
        ring[i][0] * ring[(i + 1) % n][1] - ring[(i + 1) % n][0] * ring[i][1] for i in range(n)
    )


def check_vertex_count(rings: int, vertices: int) -> None:
    """The cap on a zone's size, checked from the counts alone, before any vertex is read."""
    if vertices > MAX_ZONE_VERTICES:
        raise ZoneGeometryError(
            f"the zone has {vertices} vertices in {rings} rings; at most "
            f"{MAX_ZONE_VERTICES} in all (MAX_ZONE_VERTICES): simplify its outline "
            "or split it into several zones"
        )


def check_coordinate(name: str, value: float) -> None:
    """A finite number of metres, near enough to the map to be meant."""
    if not math.isfinite(value) or abs(value) > MAX_COORDINATE_M:
        raise ZoneGeometryError(
            f"{name} must be a finite number of metres within "
            f"{MAX_COORDINATE_M:.0f} of the map origin, not {value!r}"
        )


def _check_vertices(name: str, ring: Ring) -> None:
    """At least 3 vertices, each finite and near the map, none repeated next to itself."""
    if len(ring) < 3:
        raise ZoneGeometryError(f"{name} has {len(ring)} vertices; a polygon needs at least 3")
    for i, (x, y) in enumerate(ring):
        check_coordinate(f"{name} vertex {i} x", x)
        check_coordinate(f"{name} vertex {i} y", y)
    n = len(ring)
    for i in range(n):
        if ring[i] == ring[(i + 1) % n]:
            raise ZoneGeometryError(
                f"{name} repeats vertex {i} ({ring[i][0]}, {ring[i][1]}) "
                "next to itself; remove the duplicate (the ring closes by itself)"
            )


def _on_one_line(ring: Ring) -> bool:
    """All vertices on the line through the first and the farthest one from it."""
    pts = np.asarray(ring, dtype=np.float64)
    d = pts - pts[0]
    far = d[int(np.argmax(np.hypot(d[:, 0], d[:, 1])))]
    span = float(np.hypot(far[0], far[1]))
    offsets = np.abs(d[:, 0] * far[1] - d[:, 1] * far[0]) / span  # distance to that line
    return bool(offsets.max() <= 1e-9 * max(span, 1.0))


def _where(reason: str) -> tuple[str, str]:
    """GEOS's reason ("Self-intersection[x y]") as its kind and '(x, y)'."""
    match = _REASON.match(reason)
    if match is None:
        return reason, ""
    return match["kind"], f"({float(match['x']):g}, {float(match['y']):g})"


def _check_ring_shape(name: str, ring: Ring, geometry: shapely.LinearRing) -> None:
    """No crossing, no touching itself, some area: a bow-tie is a crossing, not 'no area'."""
    kind, at = _where(shapely.is_valid_reason(shapely.Polygon(geometry)))
    if kind != "Valid Geometry":
        if _on_one_line(ring) or kind == "Too few points":
            raise ZoneGeometryError(f"{name} has no area (its vertices lie on one line)")
        verb = "touches itself" if kind == "Ring Self-intersection" else "crosses itself"
        raise ZoneGeometryError(f"{name} {verb} at {at}; draw it without crossings")
    if abs(signed_area(ring)) < _NO_AREA_M2:
        raise ZoneGeometryError(f"{name} has no area (its vertices lie on one line)")


def _rings_at(point: str, names: Sequence[str], rings: Sequence[shapely.LinearRing]) -> str:
    """The rings that pass through a point GEOS named, for a message ("hole 2 and hole 5")."""
    match = re.match(r"\((\S+), (\S+)\)", point)
    if match is None:
        return "two rings"
    at = shapely.Point(float(match[1]), float(match[2]))
    near = shapely.dwithin(np.asarray(rings, dtype=object), at, 1e-6)
    found = [name for name, hit in zip(names, near, strict=True) if hit]
    return " and ".join(found[:2]) if len(found) >= 2 else "two rings"


def check_zone_rings(polygon: Ring, holes: Sequence[Ring]) -> None:
    """Raises ZoneGeometryError naming the first problem; returns for rings that draw a
    valid polygon with holes (the module's docstring has the rules)."""
    check_vertex_count(1 + len(holes), len(polygon) + sum(len(h) for h in holes))
    names = ["polygon", *(f"hole {k}" for k in range(len(holes)))]
    rings = [polygon, *holes]
    for name, ring in zip(names, rings, strict=True):
        _check_vertices(name, ring)
    geometries = [shapely.LinearRing(ring) for ring in rings]
    # One pass of GEOS's validity over the whole zone: the common, valid case costs that
    # and the areas. Only a refusal looks further, for the ring and the reason to name.
    whole = shapely.is_valid_reason(shapely.Polygon(geometries[0], geometries[1:]))
    if whole == "Valid Geometry":
        for name, ring in zip(names, rings, strict=True):
            if abs(signed_area(ring)) < _NO_AREA_M2:
                raise ZoneGeometryError(f"{name} has no area (its vertices lie on one line)")
        return
    for name, ring, geometry in zip(names, rings, geometries, strict=True):
        _check_ring_shape(name, ring, geometry)
    if not holes:
        raise ZoneGeometryError(f"the zone is not a valid area: {whole}")
    shell = shapely.Polygon(geometries[0])
    hole_areas = shapely.polygons(np.asarray(geometries[1:], dtype=object))
    inside = shapely.covers(shell, hole_areas)
    for k in np.flatnonzero(~inside):
        crossing = shapely.intersects(geometries[0], geometries[k + 1])
        if crossing:
            _, at = _where(
                shapely.is_valid_reason(shapely.Polygon(geometries[0], [geometries[k + 1]]))
            )
            raise ZoneGeometryError(
                f"hole {k} crosses the polygon's edge near {at}; a hole lies inside its "
                "zone's polygon (touching it at single points at most)"
            )
        raise ZoneGeometryError(
            f"hole {k} lies outside the polygon; a hole lies inside its zone's polygon "
            "(outside it, the even-odd rule would add its area to the zone)"
        )
    kind, at = _where(whole)
    if kind == "Holes are nested":
        raise ZoneGeometryError(
            f"a hole lies inside another hole near {at}; an island inside a hole is a zone "
            "of its own"
        )
    if kind == "Interior is disconnected":
        raise ZoneGeometryError(
            f"the holes cut the zone into separate pieces near {at}; draw each piece as a "
            "zone of its own"
        )
    if kind == "Self-intersection":
        raise ZoneGeometryError(
            f"{_rings_at(at, names, geometries)} cross or overlap near {at}; holes may "
            "touch at single points but not overlap"
        )
    raise ZoneGeometryError(f"the zone is not a valid area: {kind} {at}".rstrip())
