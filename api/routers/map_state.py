"""The map at any instant of the retention: metadata plus every chunk's winning write."""

from __future__ import annotations

import msgspec
from fastapi import APIRouter, Depends, HTTPException, Query, Response
from pydantic import BaseModel

from mapservice.ports import HistoryStore
from mapservice.render import png, stitch
from mapservice.wire2019 import format_timestamp

from ..deps import at_instant, get_store

router = APIRouter(prefix="/api/v1/map", tags=["map"])
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


@router.get("", operation_id="getMapAt", response_model=MapAt)
def get_map_at(
    at_ms: int = Depends(at_instant),
    store: HistoryStore = Depends(get_store),
) -> Response:
    meta = store.latest_meta()
    # Encoded directly (the shape is MapAt's): a whole map is ~1,500 chunks, and pydantic's
    # per-object validation and encoding cost as much as the query (a replay seek waits on it).
    body = _json.encode({
        "at_ms": at_ms,
        "meta": meta.to_2019() if meta is not None else None,
        "chunks": [{"row": c.row, "column": c.column, "timestamp": format_timestamp(c.ts_ms),
                    "ts_ms": c.ts_ms, "robotId": c.robot_id, "content_hash": c.content_hash}
                   for c in store.map_at(at_ms)],
    })
    return Response(body, media_type="application/json")


@router.get("/png", operation_id="getMapPngAt",
            responses={200: {"content": {"image/png": {}}}})
def get_map_png_at(
    at_ms: int = Depends(at_instant),
    scale: float = Query(1.0, gt=0, le=4, description="Image scale (nearest neighbour)"),
    store: HistoryStore = Depends(get_store),
) -> Response:
    meta = store.latest_meta()
    if meta is None:
        raise HTTPException(404, "no map meta stored yet; robots POST one at start-up")
    chunks = store.map_at(at_ms)
    contents = store.chunk_contents([bytes.fromhex(c.content_hash) for c in chunks])
    return Response(png(stitch(meta, chunks, contents), scale), media_type="image/png",
                    headers={"X-Map-At-Ms": str(at_ms)})
