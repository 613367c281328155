"""The store's answers to the 2019 REST contract: chunk and pose listings filtered, ordered
and paged as `core.legacy_query` parsed them.

`ClickHouseLegacyQueries` (the LegacyQueries role) reads through the
`connection.ClickHouseConnection` it holds and depends on nothing else of the store.
"""

from __future__ import annotations

from collections.abc import Callable

from mapservice.adapters.clickhouse.connection import (
    FINAL_SETTINGS,
    POSE_READ_COLUMNS,
    ClickHouseConnection,
)
from mapservice.adapters.clock import SystemClock
from mapservice.core.legacy_query import ChunkQuery, PoseQuery, sort_column
from mapservice.core.ports import ChunkRow, PoseRow


class ClickHouseLegacyQueries:
    """list_chunks, list_poses."""

    def __init__(
        self, connection: ClickHouseConnection, clock_ms: Callable[[], int] | None = None
    ) -> None:
        self.connection = connection
        # The service's clock: the newest-first listing looks for its rows just before
        # "now" on it (a simulated clock where the settings ask for one).
        self.clock_ms: Callable[[], int] = clock_ms or SystemClock().now_ms

    def list_chunks(self, query: ChunkQuery) -> list[ChunkRow]:
        rows = self._legacy_rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.connection.database}.chunk_events FINAL",
            query,
            lambda sql, params: self.connection.rows(sql, params),
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def list_poses(self, query: PoseQuery) -> list[PoseRow]:
        return self._legacy_rows(
            f"SELECT {POSE_READ_COLUMNS} FROM {self.connection.database}.poses FINAL",
            query,
            self.connection.pose_query,
        )

    def _legacy_rows(self, select: str, query: ChunkQuery | PoseQuery, run: Callable) -> list:
        """Filters only on sorting-key columns (PREWHERE keeps FINAL exact, as in poses()),
        the order from the whitelist (never the client's text), LIMIT/OFFSET as bound
        parameters. A newest-first read without a lower bound first tries the last hour,
        then day: when that window alone fills skip + limit, the answer is the same."""
        where = []
        params: dict = {"n": query.limit, "s": query.skip}
        for column, op, value in (
            ("ts", "=", query.timestamp_ms),
            ("ts", ">=", query.updated_since_ms),
            ("ts", "<", query.updated_before_ms),
        ):
            if value is not None:
                name = f"p{len(params)}"
                where.append(f"{column} {op} fromUnixTimestamp64Milli({{{name}:Int64}})")
                params[name] = value
        if query.robot_id is not None:
            where.append("robot_id = {robot:String}")
            params["robot"] = query.robot_id
        if isinstance(query, ChunkQuery):
            for column, value in (("row", query.row), ("col", query.column)):
                if value is not None:
                    where.append(f"{column} = {{{column}:UInt16}}")
                    params[column] = value
        order = ", ".join(
            f"{sort_column(f)} {'DESC' if d == 'desc' else 'ASC'}" for f, d in query.order
        )

        def sql(extra: list[str]) -> str:
            clause = f" PREWHERE {' AND '.join(where + extra)}" if where or extra else ""
            return (
                f"{select}{clause} ORDER BY {order} LIMIT {{n:UInt32}} OFFSET {{s:UInt32}} "
                f"{FINAL_SETTINGS}"
            )

        if (
            query.limit
            and query.order[0] == ("timestamp", "desc")
            and query.updated_since_ms is None
            and query.timestamp_ms is None
        ):
            upper = query.updated_before_ms or self.clock_ms()
            for span_ms in (3_600_000, 86_400_000):
                rows = run(
                    sql(["ts >= fromUnixTimestamp64Milli({lower:Int64})"]),
                    {**params, "lower": upper - span_ms},
                )
                if len(rows) == query.limit:
                    return rows
        return run(sql([]), params)
