"""Reads of the incidents found (schema v19): `ClickHouseIncidentReads`, the IncidentReader
role, over the store's connection; `incident_row` (an incident as the row the writer
inserts) and `incident_of` (a row as its incident) keep the two ends of the table alike."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import msgspec

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.incidents import Incident, PoseRef

_evidence = msgspec.json.Decoder(tuple[PoseRef, ...])
_SELECT = (
    "incident_id, kind, robots, toUnixTimestamp64Milli(start), toUnixTimestamp64Milli(end), "
    "ongoing, x, y, severity, measure, evidence"
)


def incident_row(incident: Incident, found_ms: int, retracted: bool) -> list[Any]:
    """The row of incident_schema.COLUMNS for one finding."""
    i = incident
    return [
        i.incident_id,
        i.kind,
        list(i.robots),
        i.start_ms,
        i.end_ms,
        i.ongoing,
        i.x,
        i.y,
        i.severity,
        i.measure,
        msgspec.json.encode(i.evidence).decode(),
        found_ms,
        retracted,
    ]


def incident_of(row: Sequence[Any]) -> Incident:
    incident_id, kind, robots, start, end, ongoing, x, y, severity, measure, evidence = row
    return Incident(
        incident_id=incident_id,
        kind=kind,
        robots=tuple(robots),
        start_ms=int(start),
        end_ms=int(end),
        ongoing=bool(ongoing),
        x=float(x),
        y=float(y),
        severity=severity,
        measure=float(measure),
        evidence=_evidence.decode(evidence),
    )


class ClickHouseIncidentReads:
    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def incidents(
        self,
        from_ms: int,
        to_ms: int,
        kinds: Sequence[str] = (),
        robot_id: str | None = None,
        limit: int = 10_000,
    ) -> list[Incident]:
        where = [
            "start < fromUnixTimestamp64Milli({to:Int64})",
            # incident_model.meets: an ongoing one's stored end is where it was last found
            "(end >= fromUnixTimestamp64Milli({f:Int64}) OR ongoing)",
            "NOT retracted",
        ]
        params: dict[str, Any] = {"f": from_ms, "to": to_ms, "n": limit}
        if kinds:
            where.append("kind IN {kinds:Array(String)}")
            params["kinds"] = list(kinds)
        if robot_id is not None:
            where.append("has(robots, {robot:String})")
            params["robot"] = robot_id
        rows = self.connection.rows(
            f"SELECT {_SELECT} FROM {self.connection.database}.incidents FINAL "
            f"WHERE {' AND '.join(where)} ORDER BY start, kind, incident_id LIMIT {{n:UInt32}}",
            params,
        )
        return [incident_of(r) for r in rows]
