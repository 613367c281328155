"""Reads of the incidents found (schema v19): `ClickHouseIncidentReads`, the IncidentReader
role, over the store's connection; `incident_row` (an incident as the row the writer
inserts) and `incident_of` (a row as its incident) keep the two ends of the table alike."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import msgspec

from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.core.heatmaps import FINEST_CELL_MM, CountedIncidents
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
        where, params = _meeting(from_ms, to_ms, kinds, robot_id)
        rows = self.connection.rows(
            f"SELECT {_SELECT} FROM {self.connection.database}.incidents FINAL "
            f"WHERE {where} ORDER BY {_ORDER} LIMIT {{n:UInt32}}",
            {**params, "n": limit},
        )
        return [incident_of(r) for r in rows]

    def incidents_per_cell(
        self, from_ms: int, to_ms: int, factor: int, limit: int = 100_000
    ) -> CountedIncidents:
        if factor < 1:
            raise ValueError("factor must be positive")
        where, params = _meeting(from_ms, to_ms)
        # The first limit + 1 as the list orders them, numbered: the cells count the first
        # `limit`, the one more says the span had more. Cells as heatmaps.incident_cells
        # places them: the place rounded half to even to the millimetre, floored to the cell.
        side = FINEST_CELL_MM * factor
        rows = self.connection.rows(
            f"SELECT toInt64(floor(roundBankers(x * 1000) / {side})) AS i, "
            f"toInt64(floor(roundBankers(y * 1000) / {side})) AS j, "
            "countIf(k <= {n:UInt32}), count() "
            "FROM (SELECT x, y, row_number() OVER (ORDER BY "
            f"{_ORDER}) AS k FROM (SELECT x, y, start, kind, incident_id "
            f"FROM {self.connection.database}.incidents FINAL WHERE {where} "
            f"ORDER BY {_ORDER} LIMIT {{n:UInt32}} + 1)) GROUP BY i, j {FINAL_SETTINGS}",
            {**params, "n": limit},
        )
        cells = {(int(i), int(j)): int(n) for i, j, n, _ in rows if n}
        return CountedIncidents(cells, sum(int(every) for *_, every in rows) > limit)


_ORDER = "start, kind, incident_id"


def _meeting(
    from_ms: int, to_ms: int, kinds: Sequence[str] = (), robot_id: str | None = None
) -> tuple[str, dict[str, Any]]:
    """The WHERE of the incidents meeting [from_ms, to_ms) of `kinds` and with `robot_id`,
    and its parameters."""
    where = [
        "start < fromUnixTimestamp64Milli({to:Int64})",
        # incident_model.meets: an ongoing one's stored end is where it was last found
        "(end >= fromUnixTimestamp64Milli({f:Int64}) OR ongoing)",
        "NOT retracted",
    ]
    params: dict[str, Any] = {"f": from_ms, "to": to_ms}
    if kinds:
        where.append("kind IN {kinds:Array(String)}")
        params["kinds"] = list(kinds)
    if robot_id is not None:
        where.append("has(robots, {robot:String})")
        params["robot"] = robot_id
    return " AND ".join(where), params
