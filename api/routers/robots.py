"""Every robot at any instant of the retention: its latest pose and status, with age."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.ports import Clock, HistoryStore
from mapservice.settings import Settings
from mapservice.wire2019 import format_timestamp

from ..deps import get_clock, get_settings, get_store, parse_instant
from .poses import Pose

router = APIRouter(prefix="/api/v1/robots", tags=["robots"])


class RobotAt(Pose):
    age_ms: int


class RobotsAt(BaseModel):
    at_ms: int
    robots: list[RobotAt]


@router.get("", operation_id="getRobotsAt", response_model=RobotsAt)
def get_robots_at(
    at: str | None = Query(None, description="Instant (ISO 8601 or epoch ms); default now"),
    store: HistoryStore = Depends(get_store),
    settings: Settings = Depends(get_settings),
    clock: Clock = Depends(get_clock),
) -> RobotsAt:
    now = clock.now_ms()
    at_ms = parse_instant(at, settings, now) if at is not None else now
    return RobotsAt(at_ms=at_ms, robots=[
        RobotAt(robotId=r.robot_id, timestamp=format_timestamp(r.ts_ms), ts_ms=r.ts_ms,
                receive_time_ms=r.receive_time_ms, position=(r.x, r.y, r.z),
                orientation=(r.qx, r.qy, r.qz, r.qw), battery_level=r.battery_level,
                charging=r.charging, loaded=r.loaded,
                path=list(r.path) if r.path is not None else None, age_ms=at_ms - r.ts_ms)
        for r in store.robots_at(at_ms)])
