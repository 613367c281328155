"""The store's reads of conflicting chunk writes: the writes near given chunks (the
conflict detector's look-back after a restart), the recorded conflicts of a window, and
their counts per timeline bucket; on the read client.

`ClickHouseConflictReads` (the ConflictReader role) holds the connection only, never
another role's queries.
"""

from __future__ import annotations

from collections.abc import Sequence

from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.core.ports import ChunkRow, ConflictRow


class ClickHouseConflictReads:
    """Conflicts and the chunk writes they are detected from."""

    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def chunk_writes_near(
        self, chunks: Sequence[tuple[int, int]], from_ms: int, to_ms: int
    ) -> list[ChunkRow]:
        if not chunks:
            return []
        rows = self.connection.rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.connection.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts <= fromUnixTimestamp64Milli({t:Int64}) "
            "WHERE (row, col) IN (SELECT tupleElement(c, 1), tupleElement(c, 2) "
            "FROM (SELECT arrayJoin({cs:Array(Tuple(UInt16, UInt16))}) AS c)) "
            f"ORDER BY ts, row, col, robot_id {FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "cs": [tuple(c) for c in set(chunks)]},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def conflicts(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ConflictRow]:
        rows = self.connection.rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_a, toUnixTimestamp64Milli(ts_a), "
            f"robot_b FROM {self.connection.database}.conflicts FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_b LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ConflictRow(*r) for r in rows]

    def conflict_counts(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        if bucket_ms <= 0:
            raise ValueError("bucket_ms must be positive")
        # Without FINAL: count distinct identities, the same number FINAL would give.
        rows = self.connection.rows(
            "SELECT {f:Int64} + intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {b:Int64}) * {b:Int64} "
            "AS start, uniqExact(ts, row, col, robot_b) "
            f"FROM {self.connection.database}.conflicts "
            "WHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "GROUP BY start ORDER BY start",
            {"f": from_ms, "t": to_ms, "b": bucket_ms},
        )
        return {int(start): int(n) for start, n in rows}
