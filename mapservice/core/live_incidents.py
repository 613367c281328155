"""Incidents on the live stream: what the processors found or retracted, announced on the
live topic once it is stored, so a live page lists a new incident without asking again.

Each message is `{"type": "incident", "ts_ms", "retracted", "incident"}`: `ts_ms` when it
was found (the detection's clock), `incident` the incident in the shape `GET
/api/v1/incidents` lists it (an ongoing silence's end as found; the list extends it to
now), and `retracted` true when a late pose broke an incident announced before (readers
drop it by its id). The records are cut like the batches' (`live_messages.pack_records`).
"""

from __future__ import annotations

from collections.abc import Sequence

import msgspec

from mapservice.core.incident_model import Incident
from mapservice.core.live_messages import MAX_RECORD_BYTES, pack_records

INCIDENT = "incident"


class _Evidence(msgspec.Struct):
    robotId: str  # noqa: N815 - the API's field name
    ts_ms: int
    x: float
    y: float


class _Listed(msgspec.Struct):
    """An incident as GET /api/v1/incidents lists it (api/routers/incidents.py)."""

    id: str
    kind: str
    robots: list[str]
    start_ms: int
    end_ms: int
    ongoing: bool
    x: float
    y: float
    severity: str
    measure: float
    evidence: list[_Evidence]


class _LiveIncident(msgspec.Struct):
    type: str
    ts_ms: int
    retracted: bool
    incident: _Listed


def _listed(i: Incident) -> _Listed:
    return _Listed(
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
        [_Evidence(e.robot_id, e.ts_ms, e.x, e.y) for e in i.evidence],
    )


_encode = msgspec.json.Encoder().encode


def incident_records(
    found: Sequence[Incident],
    retracted: Sequence[Incident],
    found_ms: int,
    max_bytes: int = MAX_RECORD_BYTES,
) -> list[bytes]:
    """The live topic's records announcing incidents stored at `found_ms`: the retracted
    ones first (a finding that replaces one keeps its id, so a reader applying them in
    order ends with what the store holds)."""
    parts = [_encode(_LiveIncident(INCIDENT, found_ms, True, _listed(i))) for i in retracted]
    parts += [_encode(_LiveIncident(INCIDENT, found_ms, False, _listed(i))) for i in found]
    return pack_records(parts, max_bytes)
