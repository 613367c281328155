"""Zone violations: robots' stored poses inside a keep-out zone, found by the processors
(processors/zone_watch.py), in a time window, ordered by time."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from ..access import READ
from ..deps import AnnotationsDep, ClockDep, SettingsDep, WindowQuery

router = APIRouter(
    prefix="/api/v1/zone-violations", tags=["annotations"], dependencies=[Depends(READ)]
)


class Violation(BaseModel):
    ts_ms: int
    robotId: str
    zoneId: str  # the keep-out zone's annotation id
    x: float
    y: float


class Violations(BaseModel):
    from_ms: int
    to_ms: int
    violations: list[Violation]
    truncated: bool


@router.get("", operation_id="listZoneViolations", response_model=Violations)
def list_zone_violations(
    store: AnnotationsDep,
    settings: SettingsDep,
    clock: ClockDep,
    window: WindowQuery,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
) -> Violations:
    """Each stored pose that lay inside a keep-out zone (on one of its mask's pixels)."""
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    rows = store.zone_violations(f, t, limit + 1)
    return Violations(
        from_ms=f,
        to_ms=t,
        truncated=len(rows) > limit,
        violations=[
            Violation(ts_ms=v.ts_ms, robotId=v.robot_id, zoneId=v.annotation_id, x=v.x, y=v.y)
            for v in rows[:limit]
        ],
    )
