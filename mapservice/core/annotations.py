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

from mapservice.core.zone_geometry import (
    MAX_COORDINATE_M,
    Point,
    Ring,
    ZoneGeometryError,
    check_coordinate,
    check_vertex_count,
    check_zone_rings,
    signed_area,
)

__all__ = ["MAX_COORDINATE_M", "Point", "Ring", "signed_area"]

POI_KINDS = ("station", "charger", "door", "note")
ZONE_KINDS = ("keep_out", "speed_limit", "note")
SPEED_UNITS = ("percent", "m/s")
MAX_NAME_CHARS = 200
MAX_NOTE_CHARS = 2_000
MAX_ID_CHARS = 100


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
    try:
        check_coordinate(name, value)
    except ZoneGeometryError as exc:
        raise AnnotationError(str(exc)) from None


def _text(name: str, value: str, limit: int, required: bool) -> None:
    if required and not value.strip():
        raise AnnotationError(f"{name} must not be empty")
    if len(value) > limit:
        raise AnnotationError(f"{name} has {len(value)} characters; at most {limit}")


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
    try:
        check_zone_rings(annotation.polygon, annotation.holes)
    except ZoneGeometryError as exc:
        raise AnnotationError(str(exc)) from None
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


def _check_size(polygon: object, holes: object) -> None:
    """The cap on vertices from the lists' lengths, before a vertex is converted."""
    rings = [polygon, *(holes if isinstance(holes, (list, tuple)) else ())]
    sizes = [len(r) for r in rings if isinstance(r, (list, tuple))]
    try:
        check_vertex_count(len(sizes), sum(sizes))
    except ZoneGeometryError as exc:
        raise AnnotationError(str(exc)) from None


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
            if check:
                _check_size(doc.get("polygon"), doc.get("holes"))
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
