"""Incidents: what went wrong on the floor, found by the processors from the robots' poses
(the rules in mapservice/core/incidents.py: near misses, stuck and silent robots, low
batteries) and the records stored beside them (event_incidents.py: keep-out zone violations,
map conflicts, VDA 5050 FATAL errors and disconnections, failed commands), meeting a time
window, by start; filtered by kind and robot. An ongoing silence or disconnection lasts up
to now: its end and length are read as of now (the store keeps when it was last found)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query, Response
from pydantic import BaseModel

from mapservice.core.event_incidents import grows_with_the_clock
from mapservice.core.incident_model import KINDS
from mapservice.core.incidents import Incident as FoundIncident

from ..access import READ
from ..deps import ClockDep, IncidentsDep, SettingsDep, WindowQuery
from ..json_rows import JsonRows

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


# The page's JSON without a pydantic model per incident and per evidence (json_rows): a
# week's first page of 5,000 took ~60 µs an incident to build as models.
_EVIDENCE = JsonRows(Evidence)
_INCIDENT = JsonRows(Incident)
_PAGE = JsonRows(Incidents)


def _as_of(i: FoundIncident, now_ms: int) -> Any:
    """`Incident`'s row (json_rows) of a found incident, its end and length as of now."""
    end, measure = i.end_ms, i.measure
    if grows_with_the_clock(i) and now_ms > end:
        end, measure = now_ms, (now_ms - i.start_ms) / 1000
    return _INCIDENT.struct(
        i.incident_id,
        i.kind,
        list(i.robots),
        i.start_ms,
        end,
        i.ongoing,
        i.x,
        i.y,
        i.severity,
        measure,
        [_EVIDENCE.struct(e.robot_id, e.ts_ms, e.x, e.y) for e in i.evidence],
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
) -> Response:
    """The incidents meeting the window (begun before its end, not ended before its start)."""
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    rows = store.incidents(f, t, list(kind or ()), robot, limit + 1)
    now = clock.now_ms()
    return _PAGE.response(
        _PAGE.struct(f, t, [_as_of(i, now) for i in rows[:limit]], len(rows) > limit)
    )
