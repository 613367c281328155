"""Exports of a time window: the analysts' views as CSV or Parquet, and the map and robots
as an MCAP file that Foxglove or Lichtblick replays."""

from __future__ import annotations

import io
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.responses import Response

from mapservice.adapters.exports import TABLE_FORMATS, TABLES, export_mcap, export_table
from mapservice.core.ports import HistoryStore

from ..access import READ
from ..deps import get_store, parse_window

router = APIRouter(prefix="/api/v1/exports", tags=["exports"],
                   dependencies=[Depends(READ)])
MAX_TABLE_SPAN_MS = 7 * 86_400_000
MAX_MCAP_SPAN_MS = 86_400_000
Dataset = Literal["robot-poses", "chunk-changes", "chunk-conflicts", "dead-letters"]


def _filename(stem: str, from_ms: int, to_ms: int, ext: str) -> dict[str, str]:
    return {"Content-Disposition": f'attachment; filename="{stem}-{from_ms}-{to_ms}.{ext}"'}


@router.get("/tables/{dataset}", operation_id="exportTable", response_class=Response,
            responses={200: {"content": {"text/csv": {}, "application/vnd.apache.parquet": {}}}})
def export_table_route(
    dataset: Dataset,
    from_: str = Query(..., alias="from", description="Start (inclusive), ISO 8601 or epoch ms"),
    to: str = Query(..., description="End (exclusive), ISO 8601 or epoch ms; at most 7 days after from"),
    format: Literal["csv", "parquet"] = Query("csv", description="csv (with a header) or parquet"),
    robot_id: str | None = Query(None, alias="robotId", max_length=64,
                                 description="Only this robot (not for dead-letters)"),
    store: HistoryStore = Depends(get_store),
) -> Response:
    """Rows of an analysts' view (docs/analysts.md) in the window, as ClickHouse writes them."""
    f, t = parse_window(from_, to, MAX_TABLE_SPAN_MS)
    if not hasattr(store, "export_query"):
        raise HTTPException(501, "table exports need the ClickHouse store")
    body = export_table(store, dataset, format, f, t, robot_id)
    return Response(body, media_type=TABLE_FORMATS[format][1],
                    headers=_filename(TABLES[dataset][0], f, t, format))


@router.get("/replay.mcap", operation_id="exportReplayMcap", response_class=Response,
            responses={200: {"content": {"application/x-mcap": {}}}})
def export_replay_mcap(
    from_: str = Query(..., alias="from", description="Start (inclusive), ISO 8601 or epoch ms"),
    to: str = Query(..., description="End (exclusive); at most 24 hours after from"),
    store: HistoryStore = Depends(get_store),
) -> Response:
    """The map (`/map`, foxglove.Grid) and every robot (`/robots/<id>/pose`,
    foxglove.PoseInFrame) in the window, as MCAP for Foxglove or Lichtblick."""
    f, t = parse_window(from_, to, MAX_MCAP_SPAN_MS)
    out = io.BytesIO()
    try:
        export_mcap(store, f, t, out)
    except ValueError as exc:
        raise HTTPException(409, str(exc)) from exc
    return Response(out.getvalue(), media_type="application/x-mcap",
                    headers=_filename("replay", f, t, "mcap"))
