"""The map at any instant of the retention: metadata plus every chunk's winning write."""

from __future__ import annotations

from typing import Literal

import msgspec
from fastapi import APIRouter, Depends, HTTPException, Query, Response
from pydantic import BaseModel

from mapservice.core.render import png, stitch
from mapservice.core.wire2019 import format_timestamps

from ..access import READ
from ..deps import AtDep, HistoryDep

router = APIRouter(prefix="/api/v1/map", tags=["map"], dependencies=[Depends(READ)])
_json = msgspec.json.Encoder()


class ChunkAt(BaseModel):
    row: int
    column: int
    timestamp: str
    ts_ms: int
    robotId: str
    content_hash: str


class MapAt(BaseModel):
    at_ms: int
    meta: dict | None
    chunks: list[ChunkAt]


COMPACT_FIELDS = ("row", "column", "ts_ms", "robotId", "content_hash")


@router.get(
    "",
    operation_id="getMapAt",
    response_model=MapAt,
    description="`layout=rows` (default): the MapAt shape below. `layout=compact`: "
    "`{at_ms, meta, fields: [" + ", ".join(COMPACT_FIELDS) + "], cells: "
    "[[...], ...]}`, one array per chunk in the order of `fields` (no "
    "timestamp strings): under half the bytes, and far cheaper to encode "
    "and parse (the replay UI asks for it on every seek).",
)
def get_map_at(
    at_ms: AtDep,
    layout: Literal["rows", "compact"] = Query("rows", description="rows or compact"),
    *,
    store: HistoryDep,
) -> Response:
    meta = store.latest_meta()
    chunks = store.map_at(at_ms)
    head = {"at_ms": at_ms, "meta": meta.to_2019() if meta is not None else None}
    if layout == "compact":
        # ChunkState is an array-like struct in COMPACT_FIELDS order: no per-chunk Python.
        body = _json.encode({**head, "fields": COMPACT_FIELDS, "cells": chunks})
    else:
        # Encoded directly (the shape is MapAt's): a whole map is ~1,500 chunks, and pydantic's
        # per-object validation and encoding cost as much as the query.
        body = _json.encode(
            {
                **head,
                "chunks": [
                    {
                        "row": c.row,
                        "column": c.column,
                        "timestamp": ts,
                        "ts_ms": c.ts_ms,
                        "robotId": c.robot_id,
                        "content_hash": c.content_hash,
                    }
                    for c, ts in zip(chunks, format_timestamps([c.ts_ms for c in chunks]))
                ],
            }
        )
    return Response(body, media_type="application/json")


@router.get("/png", operation_id="getMapPngAt", responses={200: {"content": {"image/png": {}}}})
def get_map_png_at(
    at_ms: AtDep,
    scale: float = Query(1.0, gt=0, le=4, description="Image scale (nearest neighbour)"),
    *,
    store: HistoryDep,
) -> Response:
    meta = store.latest_meta()
    if meta is None:
        raise HTTPException(404, "no map meta stored yet; robots POST one at start-up")
    chunks = store.map_at(at_ms)
    contents = store.chunk_contents([bytes.fromhex(c.content_hash) for c in chunks])
    return Response(
        png(stitch(meta, chunks, contents), scale),
        media_type="image/png",
        headers={"X-Map-At-Ms": str(at_ms)},
    )
