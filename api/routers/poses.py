"""Pose history: every pose in a time window, optionally for one robot."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.core.ports import HistoryStore
from mapservice.core.wire2019 import format_timestamps

from ..access import READ
from ..deps import get_store, parse_window

router = APIRouter(prefix="/api/v1/poses", tags=["poses"],
                   dependencies=[Depends(READ)])
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


@router.get("", operation_id="listPoses", response_model=list[Pose])
def list_poses(
    from_: str = Query(..., alias="from", description="Start (inclusive), ISO 8601 or epoch ms"),
    to: str = Query(..., description="End (exclusive), ISO 8601 or epoch ms"),
    robot_id: str | None = Query(None, alias="robotId", max_length=64),
    limit: int = Query(10_000, ge=1, le=100_000),
    store: HistoryStore = Depends(get_store),
) -> list[Pose]:
    f, t = parse_window(from_, to, MAX_SPAN_MS)
    rows = store.poses(f, t, robot_id, limit)
    return [
        Pose(robotId=r.robot_id, timestamp=ts, ts_ms=r.ts_ms,
             receive_time_ms=r.receive_time_ms, position=(r.x, r.y, r.z),
             orientation=(r.qx, r.qy, r.qz, r.qw), battery_level=r.battery_level,
             charging=r.charging, loaded=r.loaded,
             path=list(r.path) if r.path is not None else None)
        for r, ts in zip(rows, format_timestamps([r.ts_ms for r in rows]))
    ]
