"""Incidents: what went wrong on the floor, found by the processors from the robots' poses
(the rules in mapservice/core/incidents.py: near misses, stuck and silent robots, low
batteries), meeting a time window, by start; filtered by kind and robot. An ongoing silence
lasts up to now: its end and length are read as of now (the store keeps when it was last
found)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.core.incidents import Incident as FoundIncident

from ..access import READ
from ..deps import ClockDep, IncidentsDep, SettingsDep, WindowQuery

router = APIRouter(prefix="/api/v1/incidents", tags=["incidents"], dependencies=[Depends(READ)])

Kind = Literal["near_miss", "stuck", "offline", "battery_low"]


class Evidence(BaseModel):
    robotId: str
    ts_ms: int
    x: float
    y: float


class Incident(BaseModel):
    id: str
    kind: Kind
    robots: list[str]
    start_ms: int
    end_ms: int
    ongoing: bool
    x: float
    y: float
    severity: Literal["warning", "critical"]
    # closest distance in m (near_miss), seconds stopped (stuck) or silent (offline),
    # lowest level in % (battery_low)
    measure: float
    evidence: list[Evidence]


class Incidents(BaseModel):
    from_ms: int
    to_ms: int
    incidents: list[Incident]
    truncated: bool


def _as_of(i: FoundIncident, now_ms: int) -> Incident:
    end, measure = i.end_ms, i.measure
    if i.kind == "offline" and i.ongoing and now_ms > end:
        end, measure = now_ms, (now_ms - i.start_ms) / 1000
    return Incident(
        id=i.incident_id,
        kind=i.kind,
        robots=list(i.robots),
        start_ms=i.start_ms,
        end_ms=end,
        ongoing=i.ongoing,
        x=i.x,
        y=i.y,
        severity=i.severity,
        measure=measure,
        evidence=[Evidence(robotId=e.robot_id, ts_ms=e.ts_ms, x=e.x, y=e.y) for e in i.evidence],
    )


@router.get("", operation_id="listIncidents", response_model=Incidents)
def list_incidents(
    store: IncidentsDep,
    settings: SettingsDep,
    clock: ClockDep,
    window: WindowQuery,
    kind: Annotated[list[Kind] | None, Query(description="Only these kinds (repeat it).")] = None,
    robot: Annotated[str | None, Query(max_length=256, description="Only those with it.")] = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
) -> Incidents:
    """The incidents meeting the window (begun before its end, not ended before its start)."""
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    rows = store.incidents(f, t, list(kind or ()), robot, limit + 1)
    now = clock.now_ms()
    return Incidents(
        from_ms=f,
        to_ms=t,
        truncated=len(rows) > limit,
        incidents=[_as_of(i, now) for i in rows[:limit]],
    )
