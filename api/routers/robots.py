"""Every robot at any instant of the retention: its latest pose and status, with age."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.core.liveview import (
    CONNECTION_STATE_HOLDS_MS,
    clock_skew_ms,
    is_online,
    skew_flagged,
)
from mapservice.core.wire2019 import format_timestamp

from ..access import READ
from ..deps import AtDep, HistoryDep, SettingsDep, VdaDep
from .poses import Pose

router = APIRouter(prefix="/api/v1/robots", tags=["robots"], dependencies=[Depends(READ)])


class RobotAt(Pose):
    age_ms: int
    # age_ms <= robot_offline_after_s, and not OFFLINE or CONNECTIONBROKEN by a VDA 5050
    # vehicle's latest connection state of the hour before
    online: bool
    clock_skew_ms: int  # receive time - event time of this pose
    clock_skew_flag: bool  # |clock_skew_ms| > clock_skew_threshold_s


class RobotsAt(BaseModel):
    at_ms: int
    robots: list[RobotAt]
    # The robotId to pass as `after` for the next page; null on the last page.
    next_after: str | None = None


MAX_PAGE = 10_000


@router.get("", operation_id="getRobotsAt", response_model=RobotsAt)
def get_robots_at(
    at_ms: AtDep,
    limit: int = Query(
        MAX_PAGE,
        ge=1,
        le=MAX_PAGE,
        description=(
            "Robots per page, in robotId order; the answer's `next_after` names the next page"
        ),
    ),
    after: str | None = Query(
        None,
        max_length=64,
        description=(
            "Only robots whose robotId sorts after this one: the previous page's `next_after`"
        ),
    ),
    *,
    store: HistoryDep,
    vda: VdaDep,
    settings: SettingsDep,
) -> RobotsAt:
    """Every robot's latest pose at `at`, a page of at most `limit` robots in robotId
    order (one page holds every robot of a fleet up to 10,000, as before pages existed)."""
    # One more than the page: whether a next page exists, without reading every robot.
    rows = store.robots_at(at_ms, after=after, limit=limit + 1)
    page = rows[:limit]
    since = at_ms - CONNECTION_STATE_HOLDS_MS
    states = vda.connection_states_at(at_ms, since, [r.robot_id for r in page])
    return RobotsAt(
        at_ms=at_ms,
        next_after=page[-1].robot_id if len(rows) > limit else None,
        robots=[
            RobotAt(
                robotId=r.robot_id,
                timestamp=format_timestamp(r.ts_ms),
                ts_ms=r.ts_ms,
                receive_time_ms=r.receive_time_ms,
                position=(r.x, r.y, r.z),
                orientation=(r.qx, r.qy, r.qz, r.qw),
                battery_level=r.battery_level,
                charging=r.charging,
                loaded=r.loaded,
                path=list(r.path) if r.path is not None else None,
                age_ms=at_ms - r.ts_ms,
                online=is_online(
                    at_ms - r.ts_ms,
                    settings.robot_offline_after_s,
                    states[r.robot_id].state if r.robot_id in states else None,
                ),
                clock_skew_ms=clock_skew_ms(r.receive_time_ms, r.ts_ms),
                clock_skew_flag=skew_flagged(
                    clock_skew_ms(r.receive_time_ms, r.ts_ms), settings.clock_skew_threshold_s
                ),
            )
            for r in page
        ],
    )
