"""Operators' annotations of the floor: points of interest and zones, as events.

An annotation is state (the floor's keep-out zones must hold however old they are), but
every create, change and removal is an immutable event with who made it and when: the
annotations at an instant are the fold of the events up to it (`fold_annotations`).

Zones are polygons in map metres (the map's frame, as poses): an outer ring and optional
holes, read with the even-odd rule (mapservice/core/zone_masks.py rasterises them).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import msgspec

POI_KINDS = ("station", "charger", "door", "note")
ZONE_KINDS = ("keep_out", "speed_limit", "note")
SPEED_UNITS = ("percent", "m/s")
MAX_RING_VERTICES = 10_000
MAX_RINGS = 10_000
MAX_NAME_CHARS = 200
MAX_NOTE_CHARS = 2_000
MAX_ID_CHARS = 100
MAX_COORDINATE_M = 1_000_000.0  # a kilometre-sized factory is 1,000 m; beyond is a typo

Point = tuple[float, float]
Ring = tuple[Point, ...]


class AnnotationError(ValueError):
    """An annotation that cannot be stored; the message says what to fix."""


class PointOfInterest(msgspec.Struct, frozen=True, gc=False, tag="poi", array_like=True):
    """A named point on the floor (metres, map frame); heading in radians, if it has one."""

    name: str
    kind: str  # POI_KINDS
    x: float
    y: float
    heading: float | None = None
    note: str = ""


class Zone(msgspec.Struct, frozen=True, gc=False, tag="zone", array_like=True):
    """An area of the floor: keep-out, a speed limit (value in `speed_unit`) or a note."""

    name: str
    kind: str  # ZONE_KINDS
    polygon: Ring  # the outer ring, at least 3 distinct vertices, not closed explicitly
    holes: tuple[Ring, ...] = ()
    speed_limit: float | None = None
    speed_unit: str | None = None  # SPEED_UNITS; set exactly when kind is speed_limit
    note: str = ""


Shape = PointOfInterest | Zone


class AnnotationCreated(
    msgspec.Struct, frozen=True, gc=False, tag="annotation.created", array_like=True
):
    """An operator created an annotation (`author`: the credential's name, never a secret)."""

    annotation_id: str
    author: str
    annotation: Shape


class AnnotationChanged(
    msgspec.Struct, frozen=True, gc=False, tag="annotation.changed", array_like=True
):
    """An operator replaced an annotation's content (the whole new content)."""

    annotation_id: str
    author: str
    annotation: Shape


class AnnotationRemoved(
    msgspec.Struct, frozen=True, gc=False, tag="annotation.removed", array_like=True
):
    annotation_id: str
    author: str


AnnotationEvent = AnnotationCreated | AnnotationChanged | AnnotationRemoved
ANNOTATION_EVENTS = (AnnotationCreated, AnnotationChanged, AnnotationRemoved)


class CurrentAnnotation(msgspec.Struct, frozen=True, gc=False):
    """An annotation as it stands at an instant: its content and who made it so, when."""

    annotation_id: str
    annotation: Shape
    created_ms: int
    created_by: str
    changed_ms: int
    changed_by: str


class ZoneViolation(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """A robot's stored pose lay inside a keep-out zone (its pixel, by the masks' rule)."""

    ts_ms: int
    robot_id: str
    annotation_id: str
    x: float
    y: float


class AnnotationEdit(msgspec.Struct, frozen=True, gc=False):
    """One stored annotation event (the history of edits)."""

    ts_ms: int
    event_id: str
    event: AnnotationEvent


# --- validation ------------------------------------------------------------------------


def _finite(name: str, value: float) -> None:
    if not math.isfinite(value) or abs(value) > MAX_COORDINATE_M:
        raise AnnotationError(
            f"{name} must be a finite number of metres within "
            f"{MAX_COORDINATE_M:.0f} of the map origin, not {value!r}"
        )


def _text(name: str, value: str, limit: int, required: bool) -> None:
    if required and not value.strip():
        raise AnnotationError(f"{name} must not be empty")
    if len(value) > limit:
        raise AnnotationError(f"{name} has {len(value)} characters; at most {limit}")


def _cross(o: Point, a: Point, b: Point) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(p1: Point, p2: Point, q1: Point, q2: Point) -> bool:
    """True when the segments cross at a point inside both (touching ends is allowed)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > 0 > d2) or (d1 < 0 < d2)) and ((d3 > 0 > d4) or (d3 < 0 < d4)):
        return True
    # Collinear overlap of positive length: two edges running along each other.
    if d1 == d2 == d3 == d4 == 0:
        axis = 0 if abs(p2[0] - p1[0]) >= abs(p2[1] - p1[1]) else 1
        lo1, hi1 = sorted((p1[axis], p2[axis]))
        lo2, hi2 = sorted((q1[axis], q2[axis]))
        return min(hi1, hi2) - max(lo1, lo2) > 0
    return False


def signed_area(ring: Ring) -> float:
    """Shoelace area in m²: positive when the ring runs counter-clockwise."""
    n = len(ring)
    return 0.5 * sum(
        ring[i][0] * ring[(i + 1) % n][1] - ring[(i + 1) % n][0] * ring[i][1] for i in range(n)
    )


def check_ring(name: str, ring: Ring, check_crossings: bool = True) -> None:
    """A ring of 3 or more vertices, finite, no repeated consecutive vertex, a non-zero
    area and, when asked, no two edges crossing (a bow-tie is not an area anyone meant)."""
    if len(ring) < 3:
        raise AnnotationError(f"{name} has {len(ring)} vertices; a polygon needs at least 3")
    if len(ring) > MAX_RING_VERTICES:
        raise AnnotationError(f"{name} has {len(ring)} vertices; at most {MAX_RING_VERTICES}")
    for i, (x, y) in enumerate(ring):
        _finite(f"{name} vertex {i} x", x)
        _finite(f"{name} vertex {i} y", y)
    n = len(ring)
    for i in range(n):
        if ring[i] == ring[(i + 1) % n]:
            raise AnnotationError(
                f"{name} repeats vertex {i} ({ring[i][0]}, {ring[i][1]}) "
                "next to itself; remove the duplicate (the ring closes by itself)"
            )
    if abs(signed_area(ring)) < 1e-9:
        raise AnnotationError(f"{name} has no area (its vertices lie on one line)")
    if not check_crossings:
        return
    edges = [(ring[i], ring[(i + 1) % n]) for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            if _segments_cross(*edges[i], *edges[j]):
                raise AnnotationError(
                    f"{name} crosses itself: edge {i} ({edges[i][0]} -> {edges[i][1]}) crosses "
                    f"edge {j} ({edges[j][0]} -> {edges[j][1]}); draw it without crossings"
                )


def validate(annotation: Shape) -> None:
    """Raises AnnotationError saying what is wrong; returns for a storable annotation."""
    _text("name", annotation.name, MAX_NAME_CHARS, True)
    _text("note", annotation.note, MAX_NOTE_CHARS, False)
    if isinstance(annotation, PointOfInterest):
        if annotation.kind not in POI_KINDS:
            raise AnnotationError(
                f"a point of interest's kind is one of {', '.join(POI_KINDS)}, "
                f"not {annotation.kind!r}"
            )
        _finite("x", annotation.x)
        _finite("y", annotation.y)
        if annotation.heading is not None and not (
            math.isfinite(annotation.heading) and -2 * math.pi <= annotation.heading <= 2 * math.pi
        ):
            raise AnnotationError(f"heading is in radians, within ±2π, not {annotation.heading!r}")
        return
    if annotation.kind not in ZONE_KINDS:
        raise AnnotationError(
            f"a zone's kind is one of {', '.join(ZONE_KINDS)}, not {annotation.kind!r}"
        )
    if len(annotation.holes) + 1 > MAX_RINGS:
        raise AnnotationError(
            f"a zone has at most {MAX_RINGS} rings, not {len(annotation.holes) + 1}"
        )
    # Large traced rings (a mask's import) are checked for crossings only when small: the
    # check is quadratic, and a traced boundary cannot cross itself.
    small = len(annotation.polygon) <= 500
    check_ring("polygon", annotation.polygon, small)
    for k, hole in enumerate(annotation.holes):
        check_ring(f"hole {k}", hole, len(hole) <= 500)
    if annotation.kind == "speed_limit":
        limit, unit = annotation.speed_limit, annotation.speed_unit
        if limit is None or unit is None:
            raise AnnotationError(
                f"a speed_limit zone needs speed_limit and speed_unit ({' or '.join(SPEED_UNITS)})"
            )
        if unit not in SPEED_UNITS:
            raise AnnotationError(f"speed_unit is one of {', '.join(SPEED_UNITS)}, not {unit!r}")
        if not math.isfinite(limit) or limit <= 0:
            raise AnnotationError(
                f"speed_limit must be above 0, not {limit!r} (a zone robots "
                "may not enter is a keep_out zone)"
            )
        if unit == "percent" and limit > 100:
            raise AnnotationError(f"a speed limit in percent is at most 100, not {limit!r}")
        if unit == "m/s" and limit > 100:
            raise AnnotationError(
                f"a speed limit of {limit!r} m/s is no limit for a robot; at most 100 m/s"
            )
    elif annotation.speed_limit is not None or annotation.speed_unit is not None:
        raise AnnotationError(
            f"only speed_limit zones carry speed_limit and speed_unit, not a {annotation.kind} zone"
        )


def check_id(annotation_id: str) -> None:
    if (
        not annotation_id
        or len(annotation_id) > MAX_ID_CHARS
        or not all(c.isalnum() or c in "-_.:" for c in annotation_id)
    ):
        raise AnnotationError(
            f"an annotation id is 1 to {MAX_ID_CHARS} letters, digits or "
            f"'-_.:', not {annotation_id[:120]!r}"
        )


# --- state at an instant ---------------------------------------------------------------


def fold_annotations(edits: Iterable[AnnotationEdit], at_ms: int) -> dict[str, CurrentAnnotation]:
    """The annotations standing at `at_ms` (inclusive): every edit up to it applied in
    (time, event id) order; a change of an unknown or removed id recreates it, as a
    create would (events are facts: the store never rejects one after the API took it)."""
    out: dict[str, CurrentAnnotation] = {}
    for edit in sorted((e for e in edits if e.ts_ms <= at_ms), key=lambda e: (e.ts_ms, e.event_id)):
        ev = edit.event
        if isinstance(ev, AnnotationRemoved):
            out.pop(ev.annotation_id, None)
            continue
        before = out.get(ev.annotation_id)
        if before is None or isinstance(ev, AnnotationCreated):
            out[ev.annotation_id] = CurrentAnnotation(
                ev.annotation_id, ev.annotation, edit.ts_ms, ev.author, edit.ts_ms, ev.author
            )
        else:
            out[ev.annotation_id] = CurrentAnnotation(
                ev.annotation_id,
                ev.annotation,
                before.created_ms,
                before.created_by,
                edit.ts_ms,
                ev.author,
            )
    return out


def zones_of(current: Iterable[CurrentAnnotation]) -> list[tuple[str, Zone]]:
    return sorted(
        ((c.annotation_id, c.annotation) for c in current if isinstance(c.annotation, Zone)),
        key=lambda z: z[0],
    )


# --- the JSON form (API bodies, the stored `body` column) -------------------------------


def to_doc(shape: Shape) -> dict[str, Any]:
    """An annotation as JSON-ready builtins (the API's and the stored form)."""
    if isinstance(shape, PointOfInterest):
        return {
            "shape": "poi",
            "name": shape.name,
            "kind": shape.kind,
            "x": shape.x,
            "y": shape.y,
            "heading": shape.heading,
            "note": shape.note,
        }
    return {
        "shape": "zone",
        "name": shape.name,
        "kind": shape.kind,
        "polygon": [list(p) for p in shape.polygon],
        "holes": [[list(p) for p in hole] for hole in shape.holes],
        "speed_limit": shape.speed_limit,
        "speed_unit": shape.speed_unit,
        "note": shape.note,
    }


def _ring(value: object, name: str) -> Ring:
    if not isinstance(value, (list, tuple)):
        raise AnnotationError(f"{name} is a list of [x, y] vertices in metres")
    out = []
    for i, p in enumerate(value):
        if (
            not isinstance(p, (list, tuple))
            or len(p) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in p)
        ):
            raise AnnotationError(f"{name} vertex {i} is not an [x, y] pair of numbers")
        out.append((float(p[0]), float(p[1])))
    return tuple(out)


def from_doc(doc: dict[str, Any], check: bool = True) -> Shape:
    """An annotation from its JSON form, validated unless `check` is False (a stored one
    was validated when it was made; reads must not refuse it under later rules, nor pay
    for the check again); AnnotationError says what is wrong."""
    doc = {k: v for k, v in doc.items() if v is not None}  # null is a field left out
    try:
        if doc.get("shape") == "poi":
            heading = doc.get("heading")
            shape: Shape = PointOfInterest(
                name=str(doc["name"]),
                kind=str(doc["kind"]),
                x=float(doc["x"]),
                y=float(doc["y"]),
                heading=float(heading) if heading is not None else None,
                note=str(doc.get("note") or ""),
            )
        elif doc.get("shape") == "zone":
            limit = doc.get("speed_limit")
            shape = Zone(
                name=str(doc["name"]),
                kind=str(doc["kind"]),
                polygon=_ring(doc["polygon"], "polygon"),
                holes=tuple(_ring(h, f"hole {k}") for k, h in enumerate(doc.get("holes") or ())),
                speed_limit=float(limit) if limit is not None else None,
                speed_unit=doc.get("speed_unit"),
                note=str(doc.get("note") or ""),
            )
        else:
            raise AnnotationError(f"shape is 'poi' or 'zone', not {str(doc.get('shape'))[:40]!r}")
    except KeyError as exc:
        raise AnnotationError(f"a {doc.get('shape')} needs the field {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, AnnotationError):
            raise
        raise AnnotationError(f"a field has the wrong type: {str(exc)[:200]}") from None
    if check:
        validate(shape)
    return shape


def prune_before(edits: Iterable[AnnotationEdit], boundary_ms: int) -> list[AnnotationEdit]:
    """The edits a retention at `boundary_ms` keeps: all from the boundary on, and of the
    earlier ones each standing annotation's latest edit and its creation (what the state
    at the boundary is folded from). ClickHouse's retention step applies the same rule."""
    ordered = sorted(edits, key=lambda e: (e.ts_ms, e.event_id))
    latest: dict[str, AnnotationEdit] = {}
    started: dict[
        str, AnnotationEdit
    ] = {}  # the edit that began the current life (fold's created_ms)
    for edit in ordered:
        if edit.ts_ms > boundary_ms:
            break
        aid = edit.event.annotation_id
        if isinstance(edit.event, AnnotationRemoved):
            started.pop(aid, None)
        elif isinstance(edit.event, AnnotationCreated) or aid not in started:
            started[aid] = edit
        latest[aid] = edit
    keep: set[str] = set()
    for annotation_id, edit in latest.items():
        if not isinstance(edit.event, AnnotationRemoved):
            keep.update((edit.event_id, started[annotation_id].event_id))
    return [e for e in ordered if e.ts_ms >= boundary_ms or e.event_id in keep]


def zone_advertisement(
    annotation_id: str, change: str, ts_ms: int, author: str, public_base_url: str
) -> dict[str, Any]:
    """What robots get on the zone advertisement topic when a zone is created, changed or
    removed: which, when, by whom, and where the masks as of that edit are (nav2's
    map_server files and the CostmapFilterInfo parameters)."""
    base = f"{public_base_url.rstrip('/')}/api/v1/costmap-filters"
    return {
        "annotationId": annotation_id,
        "change": change,
        "ts_ms": ts_ms,
        "by": author,
        "keepOutMaskUrl": f"{base}/keepout/mask.yaml?at={ts_ms}",
        "keepOutPgmUrl": f"{base}/keepout/mask.pgm?at={ts_ms}",
        "keepOutFilterInfoUrl": f"{base}/keepout/filter-info.yaml?at={ts_ms}",
        "speedMaskUrl": f"{base}/speed/mask.yaml?at={ts_ms}",
        "speedPgmUrl": f"{base}/speed/mask.pgm?at={ts_ms}",
        "speedFilterInfoUrl": f"{base}/speed/filter-info.yaml?at={ts_ms}",
    }
