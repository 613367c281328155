"""The 2019 chunk service (appendix A.1), path for path, so 2019 robots work unchanged.

Writes become events on Kafka, validated by the same rules as MQTT (`wire2019`), and are
readable once the processors stored them; reads come from the history. Semantics of
every parameter: `mapservice/core/legacy_query.py` and docs/contract-2019.md.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence

import msgspec
import structlog
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from mapservice.core.events import MapMetaSet, make_envelope
from mapservice.core.intake import Intake, refusal_text
from mapservice.core.legacy_query import (
    MAX_LIMIT,
    ChunkQuery,
    QueryError,
    chunk_id,
    latest_instant,
    parse_chunk_id,
    parse_chunk_query,
    select,
)
from mapservice.core.ports import (
    LegacyQueries,
    TimeTravelReader,
)
from mapservice.core.render import chunk_pixels, png
from mapservice.core.wire2019 import Reason, Rejection, format_timestamp
from mapservice.settings import Settings

from ..access import READ, require, require_robot
from ..credentials import Scope
from ..deps import (
    AdminCaller,
    AdminDep,
    ClockDep,
    HistoryDep,
    LegacyDep,
    PostedMetaDep,
    PublisherDep,
    SettingsDep,
    WriterCaller,
)
from ..posted_meta import PostedMeta
from ..publishing import publish_and_wait

router = APIRouter(prefix="/api/chunk-service", tags=["2019 chunk service"])
log = structlog.get_logger(__name__)
META_ROBOT_ID = "api"  # the 2019 POST /meta names no robot


class LegacyChunk(BaseModel):
    """Listing 12/13; `chunk` and `type` are left out when `reduced=true`."""

    row: int
    column: int
    timestamp: str
    chunk: str | None = None
    type: str | None = None
    id: str
    robotId: str


async def _read_body(request: Request, limit: int) -> bytes:
    """The request body, refused with 413 past `limit` bytes before it is all in memory."""
    body = bytearray()
    async for part in request.stream():
        body += part
        if len(body) > limit:
            detail = f"the body exceeds the {limit}-byte limit (MAPSERVICE_MAX_MESSAGE_BYTES)"
            raise HTTPException(413, refusal_text(Rejection(Reason.OVERSIZED, detail)))
    return bytes(body)


def _index_response(index: str, doc_type: str, doc_id: str) -> dict:
    # forced_refresh is false: the write is durable on Kafka, readable once stored.
    return {
        "_index": index,
        "_type": doc_type,
        "_id": doc_id,
        "_version": 1,
        "result": "created",
        "forced_refresh": False,
        "_shards": {"total": 2, "successful": 1, "failed": 0},
        "_seq_no": 0,
        "_primary_term": 1,
    }


# --- meta ------------------------------------------------------------------------------


@router.get(
    "/meta",
    operation_id="getLegacyMeta",
    dependencies=[Depends(READ)],
    responses={404: {"description": "no meta stored yet: POST one"}},
)
def get_meta(store: HistoryDep) -> dict:
    """The stored meta.json (listing 9)."""
    meta = store.latest_meta()
    if meta is None:
        raise HTTPException(404, "no map meta stored yet; POST /api/chunk-service/meta")
    return meta.to_2019()


def _intake(settings: Settings, meta: MapMetaSet | None = None) -> Intake:
    return Intake.from_settings(settings).with_meta(meta)


def _refused(rejection: Rejection) -> HTTPException:
    """A write the gateway would dead-letter: a 400 whose detail starts with its reason."""
    return HTTPException(400, refusal_text(rejection))


_META_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "example": {
                    "comment": "# CREATOR: GIMP PNM Filter Version 1.1",
                    "width": 4800,
                    "height": 3200,
                    "max_brightness": "255",
                    "CHUNK_WIDTH": 100,
                    "CHUNK_HEIGHT": 100,
                    "CHUNK_ROWS": 32,
                    "CHUNK_COLS": 48,
                }
            }
        },
    }
}


# Section A.1.1 says robots "POSTS/PUTS" their meta.json: both are accepted.
@router.put("/meta", operation_id="putLegacyMeta", openapi_extra=_META_BODY)
@router.post("/meta", operation_id="postLegacyMeta", openapi_extra=_META_BODY)
async def post_meta(
    request: Request,
    settings: SettingsDep,
    clock: ClockDep,
    publisher: PublisherDep,
    store: HistoryDep,
    posted: PostedMetaDep,
    caller: WriterCaller,
) -> dict:
    """Stores meta.json through the event path (a map.meta_set event on Kafka); the
    gateway validates chunks against it as soon as it has read it. A robot (writer token)
    posts the first meta, as 2019 robots do; changing the map's frame once one is held (its
    size, chunk grid, resolution or origin) moves every chunk, zone and nav2 mask, so it
    needs the administrator's token."""
    body = await _read_body(request, settings.max_message_bytes)
    now = clock.now_ms()
    meta = _intake(settings).map_meta(body)
    if isinstance(meta, Rejection):
        raise _refused(meta)
    held = await run_in_threadpool(_meta_for_validation, store, posted, now)
    if held is not None:
        meta = _keeping_held_frame(meta, held)
        changed = _frame_change(held, meta)
        if changed:
            require(
                caller,
                Scope.ADMIN,
                what=f"changing the map from {held.width} x {held.height} px in "
                f"{held.chunk_width} x {held.chunk_height} chunks ({changed})",
            )
    envelope = make_envelope(META_ROBOT_ID, now, now, meta)
    await run_in_threadpool(publish_and_wait, publisher, settings, envelope)
    posted.published(now, meta)
    log.info(
        "map meta posted",
        rows=meta.chunk_rows,
        cols=meta.chunk_cols,
        chunk_width=meta.chunk_width,
        chunk_height=meta.chunk_height,
    )
    return _index_response("meta", "meta", "meta")


@router.delete("/meta", operation_id="deleteLegacyMeta")
def delete_meta(
    request: Request,
    caller: AdminCaller,
    store: AdminDep,
) -> dict:
    """Administrative: deletes the stored meta (needs the admin bearer token)."""
    removed = store.delete_meta()
    log.warning(
        "map meta deleted by administrator",
        caller=caller.name,
        address=request.client.host if request.client else None,
        removed=removed,
    )
    return {"acknowledged": True, "deleted": removed}


# --- chunks ----------------------------------------------------------------------------


# The map's frame: its size, its chunk grid, and where its pixels lie on the floor
# (resolution, origin). Zones, nav2 masks and every stored chunk are read in it.
_FRAME = (
    ("width", "px"),
    ("height", "px"),
    ("chunk_width", "px"),
    ("chunk_height", "px"),
    ("chunk_rows", ""),
    ("chunk_cols", ""),
    ("resolution", "m"),
    ("origin", ""),
)
_SIZES = ("width", "height", "chunk_width", "chunk_height", "chunk_rows", "chunk_cols")


def _keeping_held_frame(meta: MapMetaSet, held: MapMetaSet) -> MapMetaSet:
    """A 2019 robot's meta.json has no resolution or origin: re-posting the held map's
    size without them (its start-up) keeps the held ones, moving nothing and erasing
    nothing. A meta of another size is a new map: taken as posted (by the admin)."""
    if any(getattr(meta, name) != getattr(held, name) for name in _SIZES):
        return meta
    return msgspec.structs.replace(
        meta,
        resolution=held.resolution if meta.resolution is None else meta.resolution,
        origin=held.origin if meta.origin is None else meta.origin,
    )


def _frame_change(held: MapMetaSet, meta: MapMetaSet) -> str:
    """What of the frame the new meta changes ('' for nothing), for the refusal."""
    changes = []
    for name, unit in _FRAME:
        before, after = getattr(held, name), getattr(meta, name)
        if before != after:
            suffix = f" {unit}" if unit else ""
            changes.append(f"{name} from {_shown(before)}{suffix} to {_shown(after)}{suffix}")
    return ", ".join(changes)


def _shown(value: object) -> str:
    return str(list(value)) if isinstance(value, tuple) else str(value)


def _meta_for_validation(
    store: TimeTravelReader, posted: PostedMeta, now_ms: int
) -> MapMetaSet | None:
    """The stored meta, or one this API instance has just published and the processors
    have not stored yet: a robot POSTs its meta and then its chunks at once (A.1.1)."""
    return posted.for_validation(store.latest_meta(), now_ms)


@router.post(
    "/chunks",
    operation_id="postLegacyChunk",
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {
                    "example": {
                        "pgmB64compressedData": "eNrt1rERwyAQRUG36HLcjlukABzIAbKPSAcDmt...",
                        "row": 3,
                        "column": 2,
                        "timestamp": "2018-12-20T23:34:33",
                        "robotId": "lkjlkj",
                    }
                }
            },
        }
    },
)
async def post_chunk(
    request: Request,
    caller: WriterCaller,
    settings: SettingsDep,
    store: HistoryDep,
    posted: PostedMetaDep,
    clock: ClockDep,
    publisher: PublisherDep,
) -> dict:
    """Listing 10 in, listing 11 out: validated by the same intake as an MQTT
    iot/chunks/create message and written to Kafka like one."""
    body = await _read_body(request, settings.max_message_bytes)
    now = clock.now_ms()
    meta = await run_in_threadpool(_meta_for_validation, store, posted, now)
    result = _intake(settings, meta).chunk(body, now)
    if isinstance(result, Rejection):
        raise _refused(result)
    require_robot(caller, result.robot_id)
    await run_in_threadpool(publish_and_wait, publisher, settings, result)
    payload = result.payload
    return _index_response(
        "chunks",
        "chunk",
        chunk_id(payload.row, payload.column, format_timestamp(result.event_time_ms)),
    )


def _render(rows: Sequence, query: ChunkQuery, store: TimeTravelReader) -> list[dict]:
    contents = (
        {} if query.reduced else store.chunk_contents([bytes.fromhex(r.content_hash) for r in rows])
    )
    out = []
    for r in rows:
        ts = format_timestamp(r.ts_ms)
        doc: dict = {"row": r.row, "column": r.column, "timestamp": ts}
        if not query.reduced:
            found = contents.get(bytes.fromhex(r.content_hash))
            if found is None:
                chunk = None
            elif query.type == "png":
                chunk = base64.b64encode(png(chunk_pixels(*found))).decode()
            else:
                chunk = base64.b64encode(found[2]).decode()
            doc["chunk"], doc["type"] = chunk, query.type
        doc["id"] = chunk_id(r.row, r.column, ts)
        doc["robotId"] = r.robot_id
        out.append(doc)
    return out


def _query_params(request: Request) -> dict[str, str]:
    return dict(request.query_params)


@router.get(
    "/chunks",
    operation_id="listLegacyChunks",
    dependencies=[Depends(READ)],
    responses={200: {"model": list[LegacyChunk]}, 400: {"description": "malformed parameter"}},
)
def list_chunks(
    request: Request,
    store: LegacyDep,
    history: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
    row: str | None = Query(None, description="chunk row (number)"),
    column: str | None = Query(None, description="chunk column (number)"),
    timestamp: str | None = Query(None, description="exact write time (UTC ISO or epoch ms)"),
    updatedSince: str | None = Query(None, description="writes at or after this time"),
    updatedBefore: str | None = Query(
        None, description="writes before this time; with latest=true: the complete map at this time"
    ),
    sort: str | None = Query(
        None,
        description="field:asc|desc[,...] of timestamp, row, "
        "column, robotId; default timestamp:desc",
    ),
    latest: str | None = Query(None, description="only each chunk's newest write (default false)"),
    reduced: str | None = Query(None, description="leave out chunk and type (default false)"),
    type: str | None = Query(None, description="pgm_base64_compressed (default) or png"),
    limit: str | None = Query(None, description=f"default 10, at most {MAX_LIMIT}"),
    skip: str | None = Query(None, description="default 0; skip + limit at most 10000"),
    robotId: str | None = Query(None),
) -> JSONResponse:
    """Listing 12: chunk writes; `latest=true&updatedBefore=T` is the map at T, read from
    the nearest snapshot plus the events after it."""
    try:
        query = parse_chunk_query(_query_params(request))
    except QueryError as exc:
        raise HTTPException(400, str(exc)) from None
    if query.latest:
        now = clock.now_ms() + int(settings.max_future_skew_s * 1000)
        rows = select(history.map_at(latest_instant(query, now)), query, ignore_time=True)
    else:
        rows = store.list_chunks(query)
    return JSONResponse(_render(rows, query, history))


@router.delete("/chunks", operation_id="deleteLegacyChunks")
def delete_chunks(
    request: Request,
    caller: AdminCaller,
    store: AdminDep,
) -> dict:
    """Administrative: deletes every stored chunk write (needs the admin bearer token)."""
    removed = store.delete_chunks()
    log.warning(
        "chunk history deleted by administrator",
        caller=caller.name,
        address=request.client.host if request.client else None,
        removed=removed,
    )
    return {"acknowledged": True, "deleted": removed}


def _chunk_by_id(chunk_id_: str, store: LegacyQueries):
    try:
        row, column, ts_ms = parse_chunk_id(chunk_id_)
    except QueryError as exc:
        raise HTTPException(404, f"no chunk with id {chunk_id_[:120]!r}: {exc}") from None
    # Two robots writing one chunk at one instant: the 2019 id names both; the map's rule
    # (greatest robot id wins) picks the one to return.
    found = store.list_chunks(
        ChunkQuery(row=row, column=column, timestamp_ms=ts_ms, sort=(("robotId", "desc"),), limit=1)
    )
    if not found:
        raise HTTPException(404, f"no chunk with id {chunk_id_[:120]!r}")
    return found[0]


@router.get(
    "/chunks/id/{chunk_id}",
    operation_id="getLegacyChunk",
    dependencies=[Depends(READ)],
    responses={200: {"model": LegacyChunk}, 404: {"description": "no such chunk"}},
)
def get_chunk(
    chunk_id: str,
    store: LegacyDep,
    history: HistoryDep,
) -> JSONResponse:
    """Listing 13: one chunk by the id POST /chunks answered with."""
    row = _chunk_by_id(chunk_id, store)
    return JSONResponse(_render([row], ChunkQuery(), history)[0])


@router.get(
    "/chunks/id/{chunk_id}/png",
    operation_id="getLegacyChunkPng",
    dependencies=[Depends(READ)],
    responses={200: {"content": {"image/png": {}}}, 404: {"description": "no such chunk"}},
)
def get_chunk_png(
    chunk_id: str,
    store: LegacyDep,
    history: HistoryDep,
) -> Response:
    """The chunk as a greyscale PNG."""
    row = _chunk_by_id(chunk_id, store)
    found = history.chunk_content(bytes.fromhex(row.content_hash))
    if found is None:
        raise HTTPException(404, f"chunk {chunk_id[:120]!r} has no stored pixels")
    return Response(png(chunk_pixels(*found)), media_type="image/png")
