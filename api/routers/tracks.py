"""A robot's track over a window: where it was (x, y, heading) and its battery."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Path, Query
from pydantic import BaseModel

from mapservice.core.timetravel import yaw

from ..access import READ
from ..deps import ClockDep, HistoryDep, SettingsDep, WindowQuery, check_step

router = APIRouter(prefix="/api/v1/robots", tags=["robots"], dependencies=[Depends(READ)])
MAX_POINTS = 100_000
MAX_SPAN_EVERY_POSE_MS = 86_400_000


class TrackPoint(BaseModel):
    ts_ms: int
    x: float
    y: float
    yaw: float  # radians, counter-clockwise from +x, from the pose's quaternion
    battery_level: float | None


class Track(BaseModel):
    robotId: str
    from_ms: int
    to_ms: int
    points: list[TrackPoint]


@router.get(
    "/{robot_id}/track",
    operation_id="getRobotTrack",
    response_model=Track,
    description="The robot's poses in [from, to): every one (windows up to 24 h), or "
    f"with step_ms > 0 its first in every step (at most {MAX_POINTS:,} points, "
    "windows up to the retention). 404 if the robot never reported.",
)
def get_robot_track(
    robot_id: Annotated[str, Path(max_length=64)],
    window: WindowQuery,
    step_ms: int = Query(0, description="0: every pose; > 0: at most one point per step"),
    *,
    store: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> Track:
    check_step(step_ms)
    span = MAX_SPAN_EVERY_POSE_MS if step_ms == 0 else settings.retention_ms
    f, t = window.in_retention(span, settings, clock.now_ms())
    if step_ms and (t - f) // step_ms > MAX_POINTS:
        raise HTTPException(
            400,
            f"{(t - f) // step_ms:,} steps of {step_ms} ms is more than "
            f"{MAX_POINTS:,}; use step_ms >= {-(-(t - f) // MAX_POINTS)}",
        )
    rows = store.robot_track(robot_id, f, t, step_ms, limit=MAX_POINTS + 1)
    if not rows and not store.robot_known(robot_id):
        raise HTTPException(
            404,
            f"robot {robot_id!r} has no pose in the history; GET /api/v1/robots lists the robots",
        )
    return Track(
        robotId=robot_id,
        from_ms=f,
        to_ms=t,
        points=[
            TrackPoint(
                ts_ms=r.ts_ms,
                x=r.x,
                y=r.y,
                yaw=yaw(r.qx, r.qy, r.qz, r.qw),
                battery_level=r.battery_level,
            )
            for r in rows[:MAX_POINTS]
        ],
    )
