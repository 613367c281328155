"""Operators' commands to robots: pause, resume, go to a point of interest, cancel the
goal. Sending one needs the `operator` scope (an operator token or the admin's; readers
and robots may not command robots); the history of commands with the robots' answers is a
read, as every history is (the replay timeline shows it).

A command is an event on Kafka (the command topic, keyed by robot), answered 202 once
Kafka has it: the gateway delivers it on the robot's own MQTT command topic (QoS 1), the
robot's ack and outcome come back through the gateway as events, and the processors
store all three. Commands are history: they expire with the retention.
"""

from __future__ import annotations

import secrets
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from mapservice.core.annotations import PointOfInterest
from mapservice.core.commands import (
    CommandError,
    CommandIssued,
    CommandRecord,
    check_issue,
    command_records,
    vda_refusal,
)
from mapservice.core.events import make_envelope
from mapservice.core.ports import AnnotationReader
from mapservice.core.vda_ids import vehicle_of

from ..access import READ
from ..deps import (
    AnnotationsDep,
    ClockDep,
    CommandsDep,
    HistoryDep,
    OperatorCaller,
    PublisherDep,
    SettingsDep,
    WindowQuery,
)
from ..publishing import publish_and_wait

router = APIRouter(prefix="/api/v1/commands", tags=["commands"])

ROBOT_ID = r"^[A-Za-z0-9_.:@-]{1,64}$"  # the 2019 robotId rule


class CommandIn(BaseModel):
    """A command for one robot: `pause` (it stops where it is and keeps reporting there),
    `resume`, `goto_poi` (it plans to the point of interest `poiId`) or `cancel` (it drops
    its goal)."""

    robotId: str = Field(pattern=ROBOT_ID)
    kind: Literal["pause", "resume", "goto_poi", "cancel"]
    poiId: str | None = Field(
        None, max_length=100, description="goto_poi only: the point of interest"
    )
    id: str | None = Field(
        None,
        max_length=100,
        description=(
            "The command's id (letters, digits, '-_.:'); generated when left out. Sending the "
            "same id again is one command: the robot acts on it once."
        ),
    )


class Target(BaseModel):
    x: float
    y: float
    heading: float | None


class Answer(BaseModel):
    ts_ms: int  # the robot's time of the answer
    status: str  # ack: accepted | rejected; outcome: done | failed | cancelled
    reason: str


class CommandOut(BaseModel):
    commandId: str
    robotId: str
    kind: str
    poiId: str | None
    target: Target | None  # goto_poi: the point's position when the command was issued
    issuedBy: str  # the credential's name, never the token
    issued_ms: int
    ack: Answer | None = None  # None: no ack (yet, as of the window's end)
    outcome: Answer | None = None


class Commands(BaseModel):
    from_ms: int
    to_ms: int
    commands: list[CommandOut]
    truncated: bool


def _out(command: CommandIssued, ts_ms: int, record: CommandRecord | None = None) -> CommandOut:
    target = (
        Target(x=command.x, y=command.y, heading=command.heading)
        if command.x is not None and command.y is not None
        else None
    )
    ack = outcome = None
    if record is not None and record.ack is not None:
        ack = Answer(ts_ms=record.ack[0], status=record.ack[1].status, reason=record.ack[1].reason)
    if record is not None and record.outcome is not None:
        outcome = Answer(
            ts_ms=record.outcome[0],
            status=record.outcome[1].outcome,
            reason=record.outcome[1].reason,
        )
    return CommandOut(
        commandId=command.command_id,
        robotId=command.robot_id,
        kind=command.kind,
        poiId=command.poi_id,
        target=target,
        issuedBy=command.issued_by,
        issued_ms=ts_ms,
        ack=ack,
        outcome=outcome,
    )


def _poi(store: AnnotationReader, poi_id: str, now_ms: int) -> PointOfInterest:
    current = {c.annotation_id: c.annotation for c in store.annotations_at(now_ms)}
    found: Any = current.get(poi_id)
    if found is None:
        raise HTTPException(
            404,
            f"no point of interest {poi_id[:100]!r} stands now (list them "
            "with GET /api/v1/annotations)",
        )
    if not isinstance(found, PointOfInterest):
        raise HTTPException(
            422, f"annotation {poi_id[:100]!r} is a zone; goto_poi needs a point of interest"
        )
    return found


@router.post("", operation_id="sendCommand", response_model=CommandOut, status_code=202)
async def send_command(
    body: CommandIn,
    caller: OperatorCaller,
    history: HistoryDep,
    annotations: AnnotationsDep,
    settings: SettingsDep,
    clock: ClockDep,
    publisher: PublisherDep,
) -> CommandOut:
    """Sends a command to a robot (202: Kafka has it; the gateway delivers it at once on
    the robot's command topic). Its ack and outcome appear in GET /api/v1/commands."""
    if not await run_in_threadpool(history.robot_known, body.robotId):
        raise HTTPException(
            404,
            f"robot {body.robotId!r} has reported no pose within the "
            "retention; list the robots with GET /api/v1/robots",
        )
    if body.kind == "goto_poi" and not body.poiId:
        raise HTTPException(422, "a goto_poi command needs poiId, the point of interest to go to")
    if body.kind != "goto_poi" and body.poiId is not None:
        raise HTTPException(422, f"only goto_poi takes a poiId, not {body.kind}")
    if settings.vda5050_interface and vehicle_of(body.robotId) is not None:
        refused = vda_refusal(body.kind)
        if refused is not None:
            raise HTTPException(422, f"robot {body.robotId!r} is a VDA 5050 vehicle: {refused}")
    now = clock.now_ms()
    poi = await run_in_threadpool(_poi, annotations, body.poiId, now) if body.poiId else None
    command = CommandIssued(
        command_id=body.id or f"c-{secrets.token_hex(8)}",
        robot_id=body.robotId,
        kind=body.kind,
        issued_by=caller.name,
        issued_at_ms=now,
        poi_id=body.poiId,
        x=poi.x if poi else None,
        y=poi.y if poi else None,
        heading=poi.heading if poi else None,
    )
    try:
        check_issue(command)
    except CommandError as exc:
        raise HTTPException(422, str(exc)) from None
    envelope = make_envelope(body.robotId, now, now, command)
    await run_in_threadpool(publish_and_wait, publisher, settings, envelope)
    return _out(command, now)


@router.get("", operation_id="listCommands", response_model=Commands, dependencies=[Depends(READ)])
def list_commands(
    store: CommandsDep,
    settings: SettingsDep,
    clock: ClockDep,
    window: WindowQuery,
    robot: Annotated[str | None, Query(pattern=ROBOT_ID, description="Only this robot's")] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1_000,
) -> Commands:
    """The commands issued in the window, oldest first, each with the robot's ack and
    outcome as far as they came before the window's end (what the replay shows at its end)."""
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    # Three events at most per command; a window holding more is cut at the limit.
    events = store.command_events(f, t, robot, 3 * limit + 1)
    records = command_records(events)
    return Commands(
        from_ms=f,
        to_ms=t,
        truncated=len(records) > limit or len(events) > 3 * limit,
        commands=[_out(r.command, r.ts_ms, r) for r in records[:limit]],
    )
