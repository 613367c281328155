"""Pose history: every pose in a time window, optionally for one robot."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Response
from pydantic import BaseModel

from mapservice.core.wire2019 import format_timestamps

from ..access import READ
from ..deps import HistoryDep, WindowQuery
from ..json_rows import JsonRows

router = APIRouter(prefix="/api/v1/poses", tags=["poses"], dependencies=[Depends(READ)])
MAX_SPAN_MS = 86_400_000


class Pose(BaseModel):
    robotId: str
    timestamp: str
    ts_ms: int
    receive_time_ms: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    battery_level: float | None
    charging: bool | str | None
    loaded: bool | str | None
    path: list[tuple[float, float]] | None


_ROWS = JsonRows(Pose)


@router.get("", operation_id="listPoses", response_model=list[Pose])
def list_poses(
    window: WindowQuery,
    robot_id: str | None = Query(None, alias="robotId", max_length=64),
    limit: int = Query(10_000, ge=1, le=100_000),
    *,
    store: HistoryDep,
) -> Response:
    f, t = window.parse(MAX_SPAN_MS)
    rows = store.poses(f, t, robot_id, limit)
    # `Pose`'s JSON without a pydantic model per row (json_rows).
    return _ROWS.response(
        [
            _ROWS.struct(
                r.robot_id,
                ts,
                r.ts_ms,
                r.receive_time_ms,
                (float(r.x), float(r.y), float(r.z)),
                (float(r.qx), float(r.qy), float(r.qz), float(r.qw)),
                float(r.battery_level) if r.battery_level is not None else None,
                r.charging,
                r.loaded,
                r.path,
            )
            for r, ts in zip(rows, format_timestamps([r.ts_ms for r in rows]))
        ]
    )
