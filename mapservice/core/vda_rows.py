"""The rows a VdaReader (ports.py, which names them) answers with: a VDA 5050 vehicle's
errors, connection states and factsheets."""

from __future__ import annotations

import msgspec


class VdaErrorRow(msgspec.Struct, frozen=True, gc=False):
    ts_ms: int
    level: str
    type: str
    description: str


class VdaConnectionRow(msgspec.Struct, frozen=True, gc=False):
    ts_ms: int  # when the state holds (a CONNECTIONBROKEN: when it was received)
    state: str  # ONLINE, OFFLINE, CONNECTIONBROKEN
    sent_ms: int  # the message's own timestamp


class VdaFactsheetRow(msgspec.Struct, frozen=True, gc=False):
    ts_ms: int
    vda_version: str
    factsheet: str  # the JSON the vehicle sent


class VdaFacts(msgspec.Struct, frozen=True, gc=False):
    """A VDA 5050 vehicle's facts beyond its poses, in [from, to), oldest first."""

    errors: list[VdaErrorRow]
    connections: list[VdaConnectionRow]
    factsheet: VdaFactsheetRow | None  # the latest before `to`
    # States without errors right after a state with some: the errors of a state hold
    # until the next state, so these end them (the errors at T are those of the latest
    # error instant or clear at or before T).
    error_clears: list[int] = []
