"""Reads of the VDA 5050 tables (schema v12): a vehicle's errors, connection states and
latest factsheet."""

from __future__ import annotations

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.ports import VdaConnectionRow, VdaErrorRow, VdaFactsheetRow, VdaFacts


class VdaReadsMixin(ClickHouseConnection):
    def vda_facts(self, robot_id: str, from_ms: int, to_ms: int, limit: int = 10_000) -> VdaFacts:
        db, p = self.database, {"r": robot_id, "f": from_ms, "t": to_ms, "n": limit}
        window = ("robot_id = {r:String} AND ts >= fromUnixTimestamp64Milli({f:Int64}) "
                  "AND ts < fromUnixTimestamp64Milli({t:Int64})")
        errors = self._rows(
            f"SELECT toUnixTimestamp64Milli(ts), level, type, description FROM {db}.vda_errors "
            f"FINAL WHERE {window} ORDER BY ts, level, type, description LIMIT {{n:UInt32}}", p)
        connections = self._rows(
            f"SELECT toUnixTimestamp64Milli(ts), state, toUnixTimestamp64Milli(sent_ts) "
            f"FROM {db}.vda_connections FINAL WHERE {window} ORDER BY ts LIMIT {{n:UInt32}}", p)
        sheets = self._rows(
            f"SELECT toUnixTimestamp64Milli(ts), vda_version, factsheet FROM {db}.vda_factsheets "
            "WHERE robot_id = {r:String} AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "ORDER BY ts DESC LIMIT 1", p)
        return VdaFacts(
            errors=[VdaErrorRow(int(t), lv, ty, d) for t, lv, ty, d in errors],
            connections=[VdaConnectionRow(int(t), s, int(sent)) for t, s, sent in connections],
            factsheet=VdaFactsheetRow(int(sheets[0][0]), sheets[0][1], sheets[0][2]) if sheets else None)
