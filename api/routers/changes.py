"""The change feed: a window's map changes newest first, page by page, narrowed to an area
(a chunk row/column box or a box in map metres) and a robot. Each change names the chunk's
content before and after it (both readable at /api/v1/chunk-contents/{hash}); a map upload
(one writer's burst over many chunks: mapservice/core/change_feed.py) is one `upload`
entry and never counts as a floor change."""

from __future__ import annotations

import math
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException, Query
from pydantic import BaseModel

from mapservice.core.change_feed import (
    UPLOAD_GAP_MS,
    UPLOAD_MIN_CHUNKS,
    ChangeCursor,
    ChangeQuery,
    ChunkBox,
    WindowTooBusy,
)

from ..access import READ
from ..deps import ChangesDep, HistoryDep, SettingsDep, WindowQuery

router = APIRouter(prefix="/api/v1/changes", tags=["changes"], dependencies=[Depends(READ)])


class Change(BaseModel):
    kind: Literal["change", "upload"]
    ts_ms: int  # event time of the write (of an upload: its first write)
    row: int
    column: int
    robot_id: str
    content_hash: str  # after the write
    previous_hash: str | None  # the chunk's content before it; null: first write or an upload
    chunks: int  # 1 for a change; how many chunks an upload wrote
    end_ms: int  # an upload's last write; a change's own time


class ChangePage(BaseModel):
    from_ms: int
    to_ms: int
    upload_rule: str
    changes: list[Change]
    next: str | None  # pass as `before` for the next (older) page; null: this is the last


def _chunk_box(
    settings_meta,
    rows: tuple[int | None, int | None],
    cols: tuple[int | None, int | None],
    metres: tuple[float | None, float | None, float | None, float | None],
) -> ChunkBox | None:
    given_rc = [v is not None for v in (*rows, *cols)]
    given_m = [v is not None for v in metres]
    if any(given_rc) and any(given_m):
        raise HTTPException(
            400,
            "give the area either as rows/columns (row_min, row_max, "
            "col_min, col_max) or in metres (x_min, x_max, y_min, y_max), not both",
        )
    if any(given_rc):
        if not all(given_rc):
            raise HTTPException(400, "a chunk area needs all of row_min, row_max, col_min, col_max")
        box = ChunkBox(rows[0], rows[1], cols[0], cols[1])  # type: ignore[arg-type]
    elif any(given_m):
        if not all(given_m):
            raise HTTPException(400, "an area in metres needs all of x_min, x_max, y_min, y_max")
        meta = settings_meta()
        if meta is None:
            raise HTTPException(
                409,
                "no map meta is stored yet, so metres cannot be placed on "
                "chunks; give the area as rows/columns",
            )
        box = _metres_to_chunks(meta, *metres)  # type: ignore[arg-type]
    else:
        return None
    if box.row_min > box.row_max or box.col_min > box.col_max:
        raise HTTPException(400, "the area's minimum is above its maximum; swap them")
    return box


def _metres_to_chunks(meta, x_min: float, x_max: float, y_min: float, y_max: float) -> ChunkBox:
    """The chunks a box in map metres touches (ROS map_server: origin = the image's lower
    left pixel, image row 0 at the top)."""
    res = meta.resolution if meta.resolution and meta.resolution > 0 else 0.05
    ox, oy = (meta.origin[0], meta.origin[1]) if meta.origin else (0.0, 0.0)
    col_lo, col_hi = (x_min - ox) / res, (x_max - ox) / res
    row_lo, row_hi = meta.height - (y_max - oy) / res, meta.height - (y_min - oy) / res
    return ChunkBox(
        math.floor(row_lo / meta.chunk_height),
        math.floor(row_hi / meta.chunk_height),
        math.floor(col_lo / meta.chunk_width),
        math.floor(col_hi / meta.chunk_width),
    )


@router.get("", operation_id="listChanges", response_model=ChangePage)
def list_changes(
    store: ChangesDep,
    history: HistoryDep,
    settings: SettingsDep,
    window: WindowQuery,
    robot: str | None = Query(None, description="Only this robot's writes"),
    row_min: int | None = Query(None, ge=0),
    row_max: int | None = Query(None, ge=0),
    col_min: int | None = Query(None, ge=0),
    col_max: int | None = Query(None, ge=0),
    x_min: float | None = Query(None, description="Area in map metres (with x_max, y_min, y_max)"),
    x_max: float | None = None,
    y_min: float | None = None,
    y_max: float | None = None,
    before: str | None = Query(None, description="The previous page's `next`"),
    limit: int = Query(100, ge=1, le=1000),
    kind: Literal["change", "upload"] | None = Query(
        None, description="Only floor changes or only map uploads (the timeline marks uploads)"
    ),
) -> ChangePage:
    f, t = window.parse(settings.retention_ms)
    box = _chunk_box(
        history.latest_meta, (row_min, row_max), (col_min, col_max), (x_min, x_max, y_min, y_max)
    )
    cursor = None
    if before is not None:
        try:
            cursor = ChangeCursor.decode(before)
        except ValueError:
            raise HTTPException(
                400,
                f"'before' ({before!r}) is not a page cursor; pass the "
                "`next` of the previous page unchanged",
            ) from None
    try:
        entries = store.change_feed(ChangeQuery(f, t, robot, box, cursor, limit + 1, kind))
    except WindowTooBusy as e:
        raise HTTPException(422, str(e)) from None
    page = entries[:limit]
    return ChangePage(
        from_ms=f,
        to_ms=t,
        upload_rule=(
            f"{UPLOAD_MIN_CHUNKS} or more chunk writes by one robot with no gap over "
            f"{UPLOAD_GAP_MS / 1000:g} s are one map upload"
        ),
        changes=[Change(**{k: getattr(e, k) for k in Change.model_fields}) for e in page],
        next=ChangeCursor(*page[-1].key()).encode() if len(entries) > limit else None,
    )
