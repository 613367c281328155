"""The 2019 coordinate service (appendix A.2): robot poses in the shape of listing 17."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from mapservice.core.legacy_query import (
    MAX_LIMIT,
    QueryError,
    latest_instant,
    parse_pose_query,
    pose_id,
    select,
)
from mapservice.core.ports import PoseRow
from mapservice.core.wire2019 import format_timestamp

from ..access import READ
from ..deps import ClockDep, HistoryDep, LegacyDep, SettingsDep

router = APIRouter(
    prefix="/api/coordinate-service", tags=["2019 coordinate service"], dependencies=[Depends(READ)]
)


class LegacyRobot(BaseModel):
    """Listing 17 (plus `plannedPath` when the robot sent one)."""

    robotId: str
    timestamp: str
    pose: dict
    status: dict
    id: str = Field(alias="_id")


def legacy_pose(r: PoseRow) -> dict:
    """A stored pose in the shape robots sent it (listing 16) plus the 2019 `_id`."""
    ts = format_timestamp(r.ts_ms)
    doc: dict = {
        "robotId": r.robot_id,
        "timestamp": ts,
        "pose": {
            "position": {"x": r.x, "y": r.y, "z": r.z},
            "orientation": {"x": r.qx, "y": r.qy, "z": r.qz, "w": r.qw},
        },
        "status": {
            "battery": {"battery_level": r.battery_level, "charging": r.charging},
            "loaded": r.loaded,
        },
    }
    if r.path is not None:
        doc["plannedPath"] = [{"x": x, "y": y} for x, y in r.path]
    doc["_id"] = pose_id(r.robot_id, ts)
    return doc


@router.get(
    "/robots",
    operation_id="listLegacyRobots",
    responses={200: {"model": list[LegacyRobot]}, 400: {"description": "malformed parameter"}},
)
def list_robots(
    request: Request,
    robotId: str | None = Query(None),
    timestamp: str | None = Query(None, description="exact pose time (UTC ISO or epoch ms)"),
    updatedSince: str | None = Query(None, description="poses at or after this time"),
    updatedBefore: str | None = Query(
        None,
        description="poses before this time; with latest=true: every robot's position at this time",
    ),
    sort: str | None = Query(
        None, description="field:asc|desc[,...] of timestamp, robotId; default timestamp:desc"
    ),
    latest: str | None = Query(None, description="only each robot's newest pose (default false)"),
    limit: str | None = Query(None, description=f"default 10, at most {MAX_LIMIT}"),
    skip: str | None = Query(None, description="default 0; skip + limit at most 10000"),
    *,
    store: LegacyDep,
    history: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> JSONResponse:
    """Listing 17: poses; `latest=true&updatedBefore=T` is every robot at T (nearest
    snapshot plus the poses after it)."""
    try:
        query = parse_pose_query(dict(request.query_params))
    except QueryError as exc:
        raise HTTPException(400, str(exc)) from None
    if query.latest:
        now = clock.now_ms() + int(settings.max_future_skew_s * 1000)
        rows = select(history.robots_at(latest_instant(query, now)), query, ignore_time=True)
    else:
        rows = store.list_poses(query)
    return JSONResponse([legacy_pose(r) for r in rows])
