"""Chunk-change history: every chunk write in a time window, in event-time order."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Response
from pydantic import BaseModel

from mapservice.core.wire2019 import format_timestamps

from ..access import READ
from ..deps import HistoryDep, WindowQuery
from ..json_rows import JsonRows

router = APIRouter(
    prefix="/api/v1/chunk-events", tags=["chunk-events"], dependencies=[Depends(READ)]
)
MAX_SPAN_MS = 86_400_000


class ChunkEvent(BaseModel):
    row: int
    column: int
    timestamp: str
    ts_ms: int
    receive_time_ms: int
    robotId: str
    content_hash: str


_ROWS = JsonRows(ChunkEvent)


@router.get("", operation_id="listChunkEvents", response_model=list[ChunkEvent])
def list_chunk_events(
    window: WindowQuery,
    limit: int = Query(10_000, ge=1, le=100_000),
    *,
    store: HistoryDep,
) -> Response:
    f, t = window.parse(MAX_SPAN_MS)
    rows = store.chunk_events(f, t, limit)
    # `ChunkEvent`'s JSON without a pydantic model per row (json_rows).
    return _ROWS.response(
        [
            _ROWS.struct(
                r.row, r.column, ts, r.ts_ms, r.receive_time_ms, r.robot_id, r.content_hash
            )
            for r, ts in zip(rows, format_timestamps([r.ts_ms for r in rows]))
        ]
    )
