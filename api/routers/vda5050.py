"""A VDA 5050 vehicle's facts beyond its poses: errors and warnings (and the states that
cleared them), connection states (exact online/offline instants) and its latest factsheet;
one vehicle's, or the fleet's of a window (the replay UI's timeline marks and fleet panel)."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Path, Query
from pydantic import BaseModel

from mapservice.core.vda_facts import VdaFacts
from mapservice.core.vda_ids import vehicle_of
from mapservice.core.wire2019 import format_timestamp

from ..access import READ
from ..deps import ClockDep, SettingsDep, VdaDep, window_in_retention

router = APIRouter(prefix="/api/v1/robots", tags=["robots"], dependencies=[Depends(READ)])

FromQuery = Annotated[
    str | None,
    Query(
        alias="from",
        description=("Window start (ISO 8601 or epoch ms); default: the retention's start"),
    ),
]
ToQuery = Annotated[str | None, Query(description="Window end; default now")]


class VdaErrorOut(BaseModel):
    timestamp: str
    ts_ms: int
    level: str
    type: str
    description: str


class VdaConnectionOut(BaseModel):
    timestamp: str
    ts_ms: int  # when the state holds (CONNECTIONBROKEN: when the broker sent the last will)
    state: str
    sent_ms: int


class VdaFactsheetOut(BaseModel):
    ts_ms: int
    vda_version: str
    factsheet: dict[str, Any]


class VdaVehicle(BaseModel):
    robotId: str
    manufacturer: str
    serialNumber: str
    online: bool | None  # the latest connection state in the window is ONLINE; None: none
    errors: list[VdaErrorOut]
    connections: list[VdaConnectionOut]
    factsheet: VdaFactsheetOut | None
    # States without errors after a state with some: the errors end there.
    errorClears: list[int] = []


@router.get("/{robot_id}/vda5050", operation_id="getVdaVehicle", response_model=VdaVehicle)
def get_vda_vehicle(
    store: VdaDep,
    settings: SettingsDep,
    clock: ClockDep,
    robot_id: Annotated[
        str,
        Path(
            max_length=64,
            description=("A VDA 5050 vehicle's robot id: <manufacturer>:<serialNumber>, escaped"),
        ),
    ],
    from_: FromQuery = None,
    to: ToQuery = None,
) -> VdaVehicle:
    names = vehicle_of(robot_id)
    if names is None:
        raise HTTPException(
            404,
            f"{robot_id[:80]!r} is not a VDA 5050 vehicle's robot id: "
            "<manufacturer>:<serialNumber>, each escaped (README, VDA 5050 vehicles)",
        )
    now = clock.now_ms()
    f, t = window_in_retention(
        from_ or str(now - settings.retention_ms + 60_000),
        to or str(now + 1),
        settings.retention_ms + 120_000,
        settings,
        now,
    )
    return _vehicle(robot_id, names, store.vda_facts(robot_id, f, t))


@router.get("/vda5050", operation_id="getVdaFleet", response_model=list[VdaVehicle])
def get_vda_fleet(
    store: VdaDep,
    settings: SettingsDep,
    clock: ClockDep,
    from_: FromQuery = None,
    to: ToQuery = None,
    limit: Annotated[
        int,
        Query(
            ge=1,
            le=10_000,
            description=("At most this many errors, clears and connection states per vehicle"),
        ),
    ] = 2_000,
) -> list[VdaVehicle]:
    """Every VDA 5050 vehicle with an error, a clear or a connection state in the window."""
    now = clock.now_ms()
    f, t = window_in_retention(
        from_ or str(now - settings.retention_ms + 60_000),
        to or str(now + 1),
        settings.retention_ms + 120_000,
        settings,
        now,
    )
    out = []
    for robot_id, facts in store.vda_fleet_facts(f, t, limit).items():
        names = vehicle_of(robot_id)
        if names is not None:
            out.append(_vehicle(robot_id, names, facts))
    return out


def _vehicle(robot_id: str, names: tuple[str, str], facts: VdaFacts) -> VdaVehicle:
    sheet = facts.factsheet
    return VdaVehicle(
        robotId=robot_id,
        manufacturer=names[0],
        serialNumber=names[1],
        online=facts.connections[-1].state == "ONLINE" if facts.connections else None,
        errors=[
            VdaErrorOut(
                timestamp=format_timestamp(e.ts_ms),
                ts_ms=e.ts_ms,
                level=e.level,
                type=e.type,
                description=e.description,
            )
            for e in facts.errors
        ],
        connections=[
            VdaConnectionOut(
                timestamp=format_timestamp(c.ts_ms), ts_ms=c.ts_ms, state=c.state, sent_ms=c.sent_ms
            )
            for c in facts.connections
        ],
        factsheet=VdaFactsheetOut(
            ts_ms=sheet.ts_ms, vda_version=sheet.vda_version, factsheet=json.loads(sheet.factsheet)
        )
        if sheet
        else None,
        errorClears=facts.error_clears,
    )
