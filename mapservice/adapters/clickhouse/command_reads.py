"""Operators' commands and the robots' answers (schema v14): their rows, and the reads
of a window of them (the replay timeline's commands): `command_row` (the writer's) and
`ClickHouseCommandReads`, the CommandReader role, over the store's connection."""

from __future__ import annotations

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.commands import (
    CommandAcknowledged,
    CommandFinished,
    CommandIssued,
    StoredCommandEvent,
)
from mapservice.core.events import Envelope

_COLUMNS = (
    "toUnixTimestamp64Milli(ts), robot_id, command_id, event, event_id, kind, status, "
    "by, poi_id, x, y, heading, reason"
)


def command_row(e: Envelope) -> list:
    """A command event as its `command_events` row (command_schema.COLUMNS' order)."""
    p = e.payload
    if isinstance(p, CommandIssued):
        return [
            e.event_time_ms,
            p.robot_id,
            p.command_id,
            "issued",
            e.event_id,
            p.kind,
            "",
            p.issued_by,
            p.poi_id or "",
            p.x,
            p.y,
            p.heading,
            "",
        ]
    if isinstance(p, CommandAcknowledged):
        return [
            e.event_time_ms,
            p.robot_id,
            p.command_id,
            "ack",
            e.event_id,
            "",
            p.status,
            p.robot_id,
            "",
            None,
            None,
            None,
            p.reason,
        ]
    assert isinstance(p, CommandFinished)
    return [
        e.event_time_ms,
        p.robot_id,
        p.command_id,
        "outcome",
        e.event_id,
        "",
        p.outcome,
        p.robot_id,
        "",
        None,
        None,
        None,
        p.reason,
    ]


def stored_of(row) -> StoredCommandEvent:
    ts, robot, command_id, event, event_id, kind, status, by, poi_id, x, y, heading, reason = row
    if event == "issued":
        return StoredCommandEvent(
            int(ts),
            event_id,
            CommandIssued(command_id, robot, kind, by, int(ts), poi_id or None, x, y, heading),
        )
    if event == "ack":
        return StoredCommandEvent(
            int(ts), event_id, CommandAcknowledged(command_id, robot, status, reason)
        )
    return StoredCommandEvent(int(ts), event_id, CommandFinished(command_id, robot, status, reason))


class ClickHouseCommandReads:
    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def command_events(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 10_000
    ) -> list[StoredCommandEvent]:
        """The commands and answers with from_ms <= time < to_ms (of one robot, if named),
        oldest first."""
        rows = self.connection.rows(
            f"SELECT {_COLUMNS} FROM {self.connection.database}.command_events FINAL "
            "WHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "AND ({r:String} = '' OR robot_id = {r:String}) "
            "ORDER BY ts, event_id LIMIT {n:UInt32}",
            {"f": from_ms, "t": to_ms, "r": robot_id or "", "n": limit},
        )
        return [stored_of(r) for r in rows]
