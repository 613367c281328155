"""The memory store's VDA 5050 facts beyond the poses: errors, connection states and
factsheets on their natural identities (as the ClickHouse tables' sort keys), and each
state's error count (vda_states)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from mapservice.core.events import (
    Envelope,
    VdaConnectionReported,
    VdaFactsheetReported,
    VdaStateReported,
)
from mapservice.core.vda_facts import VdaConnectionRow, VdaErrorRow, VdaFacts, VdaFactsheetRow


class VdaLog:
    def __init__(self) -> None:
        self._errors: dict[tuple[str, int, str, str, str], VdaErrorRow] = {}
        self._connections: dict[tuple[str, int, str], VdaConnectionRow] = {}
        self._factsheets: dict[tuple[str, int], VdaFactsheetRow] = {}
        self._error_counts: dict[tuple[str, int], int] = {}

    def append(self, e: Envelope) -> None:
        p, at, robot = e.payload, e.event_time_ms, e.robot_id
        if isinstance(p, VdaStateReported):
            self._error_counts[(robot, at)] = len(p.errors)
            for err in p.errors:
                self._errors[(robot, at, err.level, err.type, err.description)] = VdaErrorRow(
                    at, err.level, err.type, err.description
                )
        elif isinstance(p, VdaConnectionReported):
            self._connections[(robot, at, p.state)] = VdaConnectionRow(at, p.state, p.sent_time_ms)
        elif isinstance(p, VdaFactsheetReported):
            self._factsheets[(robot, at)] = VdaFactsheetRow(at, p.vda_version, p.factsheet_json)

    def vda_facts(self, robot_id: str, from_ms: int, to_ms: int, limit: int = 10_000) -> VdaFacts:
        def within(rows: dict[Any, Any]) -> list[Any]:
            return [
                v for k, v in sorted(rows.items()) if k[0] == robot_id and from_ms <= k[1] < to_ms
            ]

        sheets = [
            v for k, v in sorted(self._factsheets.items()) if k[0] == robot_id and k[1] < to_ms
        ]
        counts = sorted((k[1], n) for k, n in self._error_counts.items() if k[0] == robot_id)
        clears = [
            t
            for (_, before), (t, n) in zip(counts, counts[1:], strict=False)
            if n == 0 and before > 0 and from_ms <= t < to_ms
        ]
        return VdaFacts(
            errors=within(self._errors)[:limit],
            connections=within(self._connections)[:limit],
            factsheet=sheets[-1] if sheets else None,
            error_clears=clears[:limit],
        )

    def connection_states_at(
        self, at_ms: int, since_ms: int, robots: Sequence[str]
    ) -> dict[str, VdaConnectionRow]:
        wanted, out = set(robots), {}
        for (robot, ts, _), row in sorted(self._connections.items()):
            if robot in wanted and since_ms < ts <= at_ms:
                out[robot] = row  # the latest, of one instant the last by name
        return out

    def vda_fleet_facts(self, from_ms: int, to_ms: int, limit: int = 10_000) -> dict[str, VdaFacts]:
        robots = {
            k[0]
            for rows in (self._errors, self._connections, self._error_counts)
            for k in rows
            if from_ms <= k[1] < to_ms
        }
        facts = {r: self.vda_facts(r, from_ms, to_ms, limit) for r in sorted(robots)}
        return {r: f for r, f in facts.items() if f.errors or f.connections or f.error_clears}

    def drop_before(self, cut_ms: int) -> None:
        """The retention: errors and connection states older than `cut_ms` (keyed (robot,
        ts, ...)); factsheets and error counts are kept."""
        self._errors = {k: v for k, v in self._errors.items() if k[1] >= cut_ms}
        self._connections = {k: v for k, v in self._connections.items() if k[1] >= cut_ms}
