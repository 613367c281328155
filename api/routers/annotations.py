"""Operators' annotations of the floor: points of interest and zones, at any instant, and
their edits. Reading is a read; creating, changing and removing need the `operator` scope
(an operator token or the admin's; readers and robots may not shape the floor).

Every edit is an event on Kafka (stored by the processors, like every write), answered
once Kafka has it. The store has it a second or two later; this process answers from the
edits it published meanwhile, so an operator's own edit is seen at once.
"""

from __future__ import annotations

import base64
import binascii
import secrets
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Path, Query
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from mapservice.adapters.costmap_filters import grid_of, keep_out_pixels, read_mask
from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationEdit,
    AnnotationError,
    AnnotationRemoved,
    CurrentAnnotation,
    Shape,
    Zone,
    check_id,
    from_doc,
    to_doc,
)
from mapservice.core.events import make_envelope
from mapservice.core.ports import AnnotationReader, EventPublisher, TimeTravelReader
from mapservice.core.zone_geometry import MAX_ZONE_VERTICES, check_vertex_count
from mapservice.core.zone_masks import (
    Grid,
    ZoneMaskError,
    check_raster_cost,
    check_traceable,
    mask_to_zones,
)
from mapservice.settings import Settings

from ..access import READ
from ..annotation_state import RecentEdits, standing
from ..credentials import Caller
from ..deps import (
    AnnotationsDep,
    AtDep,
    ClockDep,
    HistoryDep,
    OperatorCaller,
    PublisherDep,
    RecentEditsDep,
    SettingsDep,
    WindowQuery,
)
from ..publishing import publish_and_wait

router = APIRouter(prefix="/api/v1/annotations", tags=["annotations"])


IdPath = Annotated[str, Path(description="The annotation's id", max_length=100)]

MAX_IMPORTED_ZONES = 5_000
CHANGES = {AnnotationCreated: "created", AnnotationChanged: "changed", AnnotationRemoved: "removed"}


class AnnotationIn(BaseModel):
    """A point of interest (`shape` poi: x, y, optional heading in radians) or a zone
    (`shape` zone: polygon of [x, y] in map metres, optional holes; a speed_limit zone has
    speed_limit and speed_unit percent or m/s). Kinds: station, charger, door, note (poi);
    keep_out, speed_limit, note (zone)."""

    shape: Literal["poi", "zone"]
    name: str = Field(max_length=200)
    kind: str = Field(max_length=40)
    x: float | None = None
    y: float | None = None
    heading: float | None = None
    polygon: list[tuple[float, float]] | None = Field(None, max_length=MAX_ZONE_VERTICES)
    holes: list[Annotated[list[tuple[float, float]], Field(max_length=MAX_ZONE_VERTICES)]] = Field(
        default_factory=list, max_length=100
    )
    speed_limit: float | None = None
    speed_unit: Literal["percent", "m/s"] | None = None
    note: str = Field("", max_length=2000)


class AnnotationCreate(AnnotationIn):
    id: str | None = Field(
        None,
        max_length=100,
        description=("The new annotation's id (letters, digits, '-_.:'); generated when left out"),
    )


class AnnotationOut(BaseModel):
    id: str
    annotation: dict[str, Any]
    created_ms: int
    created_by: str
    changed_ms: int
    changed_by: str


class Annotations(BaseModel):
    at_ms: int
    annotations: list[AnnotationOut]


class Edit(BaseModel):
    ts_ms: int
    event_id: str
    id: str
    change: Literal["created", "changed", "removed"]
    by: str
    annotation: dict[str, Any] | None  # None for a removal


class Edits(BaseModel):
    from_ms: int
    to_ms: int
    edits: list[Edit]
    truncated: bool


class MaskImport(BaseModel):
    """A nav2 keep-out mask as its map_server files: the YAML's text and the image (PGM or
    PNG) in base64. It must lie exactly over the map (same size, resolution, origin)."""

    yaml: str = Field(max_length=10_000)
    image_base64: str = Field(max_length=60_000_000)
    name: str = Field("imported keep-out", min_length=1, max_length=150)


class Imported(BaseModel):
    ids: list[str]
    at_ms: int


def _out(c: CurrentAnnotation) -> AnnotationOut:
    return AnnotationOut(
        id=c.annotation_id,
        annotation=to_doc(c.annotation),
        created_ms=c.created_ms,
        created_by=c.created_by,
        changed_ms=c.changed_ms,
        changed_by=c.changed_by,
    )


def _shape(body: AnnotationIn):
    try:
        return from_doc(body.model_dump(exclude={"id"}))
    except AnnotationError as exc:
        raise HTTPException(422, f"the annotation is not valid: {exc}") from None


async def _publish(
    recent: RecentEdits,
    publisher: EventPublisher,
    settings: Settings,
    caller: Caller,
    now_ms: int,
    event,
    after_ms: int = 0,
) -> AnnotationEdit:
    now_ms = recent.stamp(now_ms, after_ms)
    envelope = make_envelope(caller.name, now_ms, now_ms, event)
    await run_in_threadpool(publish_and_wait, publisher, settings, envelope)
    edit = AnnotationEdit(now_ms, envelope.event_id, event)
    recent.add(edit)
    return edit


def _traced_zones(body: MaskImport, grid: Grid) -> list[Zone]:
    """The mask's keep-out areas as zones, or a 422 naming the first cap it passes: the
    image's size (from its header, before decoding), its outline's length (before tracing),
    the number of zones and each zone's vertices and cells."""
    try:
        image = base64.b64decode(body.image_base64, validate=True)
        pixels = keep_out_pixels(read_mask(body.yaml, image, (grid.width, grid.height)), grid)
        check_traceable(pixels)
        zones = mask_to_zones(grid, pixels, body.name)
        if len(zones) > MAX_IMPORTED_ZONES:
            raise ValueError(
                f"the mask has {len(zones)} separate areas; at most "
                f"{MAX_IMPORTED_ZONES} are imported as zones"
            )
        for zone in zones:
            check_vertex_count(1 + len(zone.holes), len(zone.polygon) + sum(map(len, zone.holes)))
            check_raster_cost(grid, zone)
    except (binascii.Error, ValueError) as exc:
        raise HTTPException(422, f"the mask cannot be imported: {exc}") from None
    return zones


def _checked_shape(body: AnnotationIn, grid: Grid | None) -> Shape:
    """The annotation, valid and (a zone, once the map has a frame) cheap enough to
    rasterise; runs on a worker thread, as its geometry checks grow with its vertices."""
    shape = _shape(body)
    if isinstance(shape, Zone) and grid is not None:
        try:
            check_raster_cost(grid, shape)
        except ZoneMaskError as exc:
            raise HTTPException(422, f"the annotation is not valid: {exc}") from None
    return shape


async def _valid_shape(body: AnnotationIn, history: TimeTravelReader) -> Shape:
    grid = grid_of(await run_in_threadpool(history.latest_meta))
    return await run_in_threadpool(_checked_shape, body, grid)


@router.get(
    "", operation_id="listAnnotations", response_model=Annotations, dependencies=[Depends(READ)]
)
def list_annotations(recent: RecentEditsDep, store: AnnotationsDep, at: AtDep) -> Annotations:
    """The points of interest and zones standing at `at` (default now), with who created
    and last changed each, and when."""
    current = standing(recent, store, at)
    return Annotations(at_ms=at, annotations=[_out(current[k]) for k in sorted(current)])


@router.get(
    "/edits", operation_id="listAnnotationEdits", response_model=Edits, dependencies=[Depends(READ)]
)
def list_annotation_edits(
    store: AnnotationsDep,
    settings: SettingsDep,
    clock: ClockDep,
    window: WindowQuery,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
) -> Edits:
    """Every create, change and removal in the window, oldest first: the annotations' history."""
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    rows = store.annotation_edits(f, t, limit + 1)
    return Edits(
        from_ms=f,
        to_ms=t,
        truncated=len(rows) > limit,
        edits=[
            Edit(
                ts_ms=e.ts_ms,
                event_id=e.event_id,
                id=e.event.annotation_id,
                change=CHANGES[type(e.event)],
                by=e.event.author,
                annotation=None
                if isinstance(e.event, AnnotationRemoved)
                else to_doc(e.event.annotation),
            )
            for e in rows[:limit]
        ],
    )


@router.post("", operation_id="createAnnotation", response_model=AnnotationOut, status_code=201)
async def create_annotation(
    recent: RecentEditsDep,
    body: AnnotationCreate,
    caller: OperatorCaller,
    store: AnnotationsDep,
    history: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
    publisher: PublisherDep,
) -> AnnotationOut:
    """Creates a point of interest or a zone (409 if the id is taken)."""
    shape = await _valid_shape(body, history)
    annotation_id = body.id or f"a-{secrets.token_hex(8)}"
    try:
        check_id(annotation_id)
    except AnnotationError as exc:
        raise HTTPException(422, str(exc)) from None
    now = clock.now_ms()
    if annotation_id in await run_in_threadpool(standing, recent, store, now):
        raise HTTPException(
            409,
            f"annotation {annotation_id!r} exists; change it with PUT "
            f"/api/v1/annotations/{annotation_id} or choose another id",
        )
    edit = await _publish(
        recent,
        publisher,
        settings,
        caller,
        now,
        AnnotationCreated(annotation_id, caller.name, shape),
    )
    return AnnotationOut(
        id=annotation_id,
        annotation=to_doc(shape),
        created_ms=edit.ts_ms,
        created_by=caller.name,
        changed_ms=edit.ts_ms,
        changed_by=caller.name,
    )


async def _existing(
    recent: RecentEdits, store: AnnotationReader, annotation_id: str, now: int
) -> CurrentAnnotation:
    current = await run_in_threadpool(standing, recent, store, now)
    if annotation_id not in current:
        raise HTTPException(
            404,
            f"no annotation {annotation_id[:100]!r} stands now (list them "
            "with GET /api/v1/annotations; one created by another API "
            "process is there once stored, within seconds)",
        )
    return current[annotation_id]


@router.put("/{annotation_id}", operation_id="changeAnnotation", response_model=AnnotationOut)
async def change_annotation(
    recent: RecentEditsDep,
    annotation_id: IdPath,
    body: AnnotationIn,
    caller: OperatorCaller,
    store: AnnotationsDep,
    history: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
    publisher: PublisherDep,
) -> AnnotationOut:
    """Replaces an annotation's content (move, rename, reshape, another limit)."""
    shape = await _valid_shape(body, history)
    now = clock.now_ms()
    before = await _existing(recent, store, annotation_id, now)
    edit = await _publish(
        recent,
        publisher,
        settings,
        caller,
        now,
        AnnotationChanged(annotation_id, caller.name, shape),
        before.changed_ms,
    )
    return AnnotationOut(
        id=annotation_id,
        annotation=to_doc(shape),
        created_ms=before.created_ms,
        created_by=before.created_by,
        changed_ms=edit.ts_ms,
        changed_by=caller.name,
    )


@router.delete("/{annotation_id}", operation_id="removeAnnotation", status_code=204)
async def remove_annotation(
    recent: RecentEditsDep,
    annotation_id: IdPath,
    caller: OperatorCaller,
    store: AnnotationsDep,
    settings: SettingsDep,
    clock: ClockDep,
    publisher: PublisherDep,
) -> None:
    """Removes an annotation from now on (its history stays)."""
    now = clock.now_ms()
    before = await _existing(recent, store, annotation_id, now)
    await _publish(
        recent,
        publisher,
        settings,
        caller,
        now,
        AnnotationRemoved(annotation_id, caller.name),
        before.changed_ms,
    )


@router.post(
    "/import-mask", operation_id="importKeepOutMask", response_model=Imported, status_code=201
)
async def import_keep_out_mask(
    recent: RecentEditsDep,
    body: MaskImport,
    caller: OperatorCaller,
    history: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
    publisher: PublisherDep,
) -> Imported:
    """A nav2 keep-out mask as keep-out zones, one per connected area (with its holes),
    their edges on pixel edges: exporting the keep-out mask gives back its pixels."""
    grid = grid_of(await run_in_threadpool(history.latest_meta))
    if grid is None:
        raise HTTPException(
            409,
            "the map has no resolution and origin yet; upload the map "
            "(`mapservice map upload`) before importing a mask",
        )
    # Decoding, tracing and checking run on a worker thread, each step capped before the
    # next: the event loop (and with it the probes) never waits for an image.
    zones = await run_in_threadpool(_traced_zones, body, grid)
    now = clock.now_ms()
    ids = []
    for zone in zones:
        annotation_id = f"z-{secrets.token_hex(8)}"
        edit = await _publish(
            recent,
            publisher,
            settings,
            caller,
            now,
            AnnotationCreated(annotation_id, caller.name, zone),
        )
        ids.append(annotation_id)
        now = edit.ts_ms
    return Imported(ids=ids, at_ms=now)
