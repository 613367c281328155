"""Incidents: what went wrong on the floor, found by the processors from the robots' poses
(the rules in mapservice/core/incidents.py: near misses, stuck and silent robots, low
batteries) and the records stored beside them (event_incidents.py: keep-out zone violations,
map conflicts, VDA 5050 FATAL errors and disconnections, failed commands), meeting a time
window, by start; filtered by kind and robot. An ongoing silence or disconnection lasts up
to now: its end and length are read as of now (the store keeps when it was last found)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.core.event_incidents import grows_with_the_clock
from mapservice.core.incident_model import KINDS
from mapservice.core.incidents import Incident as FoundIncident

from ..access import READ
from ..deps import ClockDep, IncidentsDep, SettingsDep, WindowQuery

router = APIRouter(prefix="/api/v1/incidents", tags=["incidents"], dependencies=[Depends(READ)])

# the kinds as the rules name them (one definition: incident_model.KINDS)
Kind = Literal[KINDS]  # type: ignore[valid-type]


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
    # closest distance in m (near_miss), seconds stopped (stuck), silent or disconnected
    # (offline), inside (zone_violation), the error held (vda_error) or waited for the ack
    # (command_failed), lowest level in % (battery_low), conflicting chunk writes (conflict)
    measure: float
    evidence: list[Evidence]


class Incidents(BaseModel):
    from_ms: int
    to_ms: int
    incidents: list[Incident]
    truncated: bool


def _as_of(i: FoundIncident, now_ms: int) -> Incident:
    end, measure = i.end_ms, i.measure
    if grows_with_the_clock(i) and now_ms > end:
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
