"""The store's administration: deleting chunks and metadata, counts, bytes on disk,
OPTIMIZE, exports in ClickHouse formats, close.

`ClickHouseAdmin` (the StoreAdmin and TableExports roles) uses the clients of the
`connection.ClickHouseConnection` it holds and depends on nothing else of the store.
"""

from __future__ import annotations

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.ports import Counts


class ClickHouseAdmin:
    """Deletes, counts, storage, optimize, export, close."""

    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection
        self.database = connection.database  # what the analysts' exports name (TableExports)

    def delete_chunks(self) -> int:
        db = self.connection.database
        with self.connection.lock:
            ((removed,),) = self.connection.rows(f"SELECT count() FROM {db}.chunk_events FINAL", {})
            # TRUNCATE, not a lightweight DELETE: the whole table goes, at once and without
            # a mutation. Snapshots go too, or map_at would still answer with deleted
            # writes; their log stays, so the next snapshot builds on an empty map.
            self.connection.client.command(f"TRUNCATE TABLE {db}.chunk_events")
            self.connection.client.command(f"TRUNCATE TABLE {db}.map_snapshots")
            self.connection.client.command(
                f"TRUNCATE TABLE IF EXISTS {db}.conflicts"
            )  # derived from them
            self.connection.client.command(
                f"TRUNCATE TABLE IF EXISTS {db}.chunk_seconds"
            )  # so are these
            self.connection.client.command(f"TRUNCATE TABLE IF EXISTS {db}.chunk_bursts")
        return int(removed)

    def delete_meta(self) -> int:
        db = self.connection.database
        with self.connection.lock:
            ((removed,),) = self.connection.rows(f"SELECT count() FROM {db}.map_meta FINAL", {})
            self.connection.client.command(f"TRUNCATE TABLE {db}.map_meta")
        return int(removed)

    def counts(self) -> Counts:
        db = self.connection.database
        (row,) = self.connection.rows(
            f"SELECT (SELECT count() FROM {db}.poses FINAL), "
            f"(SELECT count() FROM {db}.chunk_events FINAL), "
            f"(SELECT uniqExact(content_hash) FROM {db}.chunk_contents), "
            f"(SELECT count() FROM {db}.dead_letters)",
            {},
        )
        return Counts(*row)

    def storage_bytes(self) -> dict[str, int]:
        """Bytes on disk per table (active parts), for benchmarks and operators."""
        rows = self.connection.rows(
            "SELECT table, sum(bytes_on_disk) FROM system.parts WHERE database = {d:String} "
            "AND active GROUP BY table",
            {"d": self.connection.database},
        )
        return {t: int(b) for t, b in rows}

    def tracked_memory_bytes(self) -> int:
        """What ClickHouse's own memory tracker counts (caches, merges, queries running):
        for embedded chDB, the part of this process's memory that ClickHouse holds."""
        (row,) = self.connection.rows(
            "SELECT value FROM system.metrics WHERE metric = 'MemoryTracking'", {}
        )
        return int(row[0])

    def optimize(self) -> None:
        """Merges parts now (and drops duplicates); benchmarks call it before measuring."""
        with self.connection.lock:
            for table in (
                "poses",
                "chunk_events",
                "chunk_contents",
                "map_meta",
                "dead_letters",
                "pose_keyframes",
                "pose_minutes",
                "pose_ten_minutes",
                "chunk_seconds",
                "chunk_bursts",
                "carried_poses",
            ):
                self.connection.client.command(
                    f"OPTIMIZE TABLE {self.connection.database}.{table} FINAL"
                )

    def export_query(self, sql: str, parameters: dict, fmt: str) -> bytes:
        """A read's result as ClickHouse writes it in `fmt` (CSVWithNames, Parquet, ...);
        mapservice/adapters/table_export.py builds `sql` from fixed names, values go as parameters."""
        with self.connection.reader() as client:
            return client.raw_query(sql, parameters=parameters, fmt=fmt)

    def close(self) -> None:
        """Closes the connection every role of this store shares."""
        self.connection.close()
