"""Reads of the VDA 5050 tables (schema v12): vehicles' errors (and the states that cleared
them), connection states and latest factsheets, of one vehicle or the whole fleet:
`ClickHouseVdaReads`, the VdaReader role, over the store's connection."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.vda_facts import VdaConnectionRow, VdaErrorRow, VdaFacts, VdaFactsheetRow


class ClickHouseVdaReads:
    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def vda_facts(self, robot_id: str, from_ms: int, to_ms: int, limit: int = 10_000) -> VdaFacts:
        return self._vda_facts(robot_id, from_ms, to_ms, limit).get(
            robot_id, VdaFacts(errors=[], connections=[], factsheet=None)
        )

    def vda_fleet_facts(self, from_ms: int, to_ms: int, limit: int = 10_000) -> dict[str, VdaFacts]:
        facts = self._vda_facts(None, from_ms, to_ms, limit)
        return {r: f for r, f in facts.items() if f.errors or f.connections or f.error_clears}

    def connection_states_at(
        self, at_ms: int, since_ms: int, robots: Sequence[str]
    ) -> dict[str, VdaConnectionRow]:
        if not robots:
            return {}
        rows = self.connection.rows(
            f"SELECT robot_id, toUnixTimestamp64Milli(ts), state, toUnixTimestamp64Milli(sent_ts) "
            f"FROM {self.connection.database}.vda_connections FINAL "
            "WHERE robot_id IN {r:Array(String)} "
            "AND ts > fromUnixTimestamp64Milli({f:Int64}) "
            "AND ts <= fromUnixTimestamp64Milli({t:Int64}) "
            "ORDER BY robot_id, ts DESC, state DESC LIMIT 1 BY robot_id",
            {"r": list(robots), "f": since_ms, "t": at_ms},
        )
        return {r: VdaConnectionRow(int(t), s, int(sent)) for r, t, s, sent in rows}

    def _vda_facts(
        self, robot_id: str | None, from_ms: int, to_ms: int, limit: int
    ) -> dict[str, VdaFacts]:
        db, p = (
            self.connection.database,
            {"r": robot_id or "", "f": from_ms, "t": to_ms, "n": limit},
        )
        robot = "robot_id = {r:String} AND " if robot_id is not None else ""
        window = (
            f"{robot}ts >= fromUnixTimestamp64Milli({{f:Int64}}) "
            "AND ts < fromUnixTimestamp64Milli({t:Int64})"
        )
        errors = self.connection.rows(
            f"SELECT robot_id, toUnixTimestamp64Milli(ts), level, type, description "
            f"FROM {db}.vda_errors FINAL WHERE {window} "
            f"ORDER BY ts, level, type, description LIMIT {{n:UInt32}} BY robot_id",
            p,
        )
        # A state without errors after one with some: the state before the window counts
        # (a clear at the window's first state).
        clears = self.connection.rows(
            f"""SELECT robot_id, toUnixTimestamp64Milli(ts) FROM (
                SELECT robot_id, ts, error_count, lagInFrame(error_count, 1, 0) OVER (
                    PARTITION BY robot_id ORDER BY ts ROWS BETWEEN 1 PRECEDING AND CURRENT ROW)
                    AS before
                FROM {db}.vda_states FINAL WHERE {robot}ts < fromUnixTimestamp64Milli({{t:Int64}})
                    AND ts >= fromUnixTimestamp64Milli({{f:Int64}}) - toIntervalHour(1))
            WHERE error_count = 0 AND before > 0 AND ts >= fromUnixTimestamp64Milli({{f:Int64}})
            ORDER BY ts LIMIT {{n:UInt32}} BY robot_id""",
            p,
        )
        connections = self.connection.rows(
            f"SELECT robot_id, toUnixTimestamp64Milli(ts), state, toUnixTimestamp64Milli(sent_ts) "
            f"FROM {db}.vda_connections FINAL WHERE {window} ORDER BY ts LIMIT {{n:UInt32}} BY robot_id",
            p,
        )
        sheets = self.connection.rows(
            f"SELECT robot_id, toUnixTimestamp64Milli(ts), vda_version, factsheet FROM {db}.vda_factsheets "
            f"WHERE {robot}ts < fromUnixTimestamp64Milli({{t:Int64}}) "
            "ORDER BY ts DESC LIMIT 1 BY robot_id",
            p,
        )
        by_robot: dict[str, dict[str, list]] = defaultdict(lambda: {"e": [], "c": [], "x": []})
        for r, t, lv, ty, d in errors:
            by_robot[r]["e"].append(VdaErrorRow(int(t), lv, ty, d))
        for r, t in clears:
            by_robot[r]["x"].append(int(t))
        for r, t, s, sent in connections:
            by_robot[r]["c"].append(VdaConnectionRow(int(t), s, int(sent)))
        factsheets = {r: VdaFactsheetRow(int(t), v, f) for r, t, v, f in sheets}
        return {
            r: VdaFacts(
                errors=by_robot[r]["e"],
                connections=by_robot[r]["c"],
                factsheet=factsheets.get(r),
                error_clears=by_robot[r]["x"],
            )
            for r in sorted(set(by_robot) | set(factsheets))
        }
