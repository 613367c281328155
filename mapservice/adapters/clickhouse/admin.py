"""The store's administration: deleting chunks and metadata, counts, bytes on disk,
OPTIMIZE, a readiness ping on a client of its own, exports in ClickHouse formats, close.

`AdminMixin` uses the clients of `connection.ClickHouseConnection` and depends on nothing
else of the store.
"""

from __future__ import annotations

import clickhouse_connect

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.ports import Counts


class AdminMixin(ClickHouseConnection):
    """Deletes, counts, storage, optimize, ping, export, close."""

    _ping_client: object | None

    def delete_chunks(self) -> int:
        db = self.database
        with self._lock:
            ((removed,),) = self._rows(f"SELECT count() FROM {db}.chunk_events FINAL", {})
            # TRUNCATE, not a lightweight DELETE: the whole table goes, at once and without
            # a mutation. Snapshots go too, or map_at would still answer with deleted
            # writes; their log stays, so the next snapshot builds on an empty map.
            self.client.command(f"TRUNCATE TABLE {db}.chunk_events")
            self.client.command(f"TRUNCATE TABLE {db}.map_snapshots")
            self.client.command(f"TRUNCATE TABLE IF EXISTS {db}.conflicts")  # derived from them
            self.client.command(f"TRUNCATE TABLE IF EXISTS {db}.chunk_seconds")  # so are these
            self.client.command(f"TRUNCATE TABLE IF EXISTS {db}.chunk_bursts")
        return int(removed)

    def delete_meta(self) -> int:
        db = self.database
        with self._lock:
            ((removed,),) = self._rows(f"SELECT count() FROM {db}.map_meta FINAL", {})
            self.client.command(f"TRUNCATE TABLE {db}.map_meta")
        return int(removed)

    def counts(self) -> Counts:
        db = self.database
        (row,) = self._rows(
            f"SELECT (SELECT count() FROM {db}.poses FINAL), "
            f"(SELECT count() FROM {db}.chunk_events FINAL), "
            f"(SELECT uniqExact(content_hash) FROM {db}.chunk_contents), "
            f"(SELECT count() FROM {db}.dead_letters)",
            {},
        )
        return Counts(*row)

    def storage_bytes(self) -> dict[str, int]:
        """Bytes on disk per table (active parts), for benchmarks and operators."""
        rows = self._rows(
            "SELECT table, sum(bytes_on_disk) FROM system.parts WHERE database = {d:String} "
            "AND active GROUP BY table",
            {"d": self.database},
        )
        return {t: int(b) for t, b in rows}

    def tracked_memory_bytes(self) -> int:
        """What ClickHouse's own memory tracker counts (caches, merges, queries running):
        for embedded chDB, the part of this process's memory that ClickHouse holds."""
        (row,) = self._rows("SELECT value FROM system.metrics WHERE metric = 'MemoryTracking'", {})
        return int(row[0])

    def optimize(self) -> None:
        """Merges parts now (and drops duplicates); benchmarks call it before measuring."""
        with self._lock:
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
                self.client.command(f"OPTIMIZE TABLE {self.database}.{table} FINAL")

    def ping(self, timeout_s: float = 2.0) -> bool:
        """A real round trip to ClickHouse on a client of its own (a hung server must not
        hold the read or write client); readiness calls it through a CachedCheck."""
        if self._ping_client is None:
            if self.dsn.startswith("chdb://"):
                self._ping_client = self._connect()
            else:
                self._ping_client = clickhouse_connect.get_client(
                    dsn=self.dsn,
                    username=self._username,
                    password=self._password,
                    connect_timeout=timeout_s,
                    send_receive_timeout=timeout_s,
                    **self.tls,
                )
        return self._ping_client.command("SELECT 1") == 1

    def export_query(self, sql: str, parameters: dict, fmt: str) -> bytes:
        """A read's result as ClickHouse writes it in `fmt` (CSVWithNames, Parquet, ...);
        mapservice/adapters/table_export.py builds `sql` from fixed names, values go as parameters."""
        with self._reader() as client:
            return client.raw_query(sql, parameters=parameters, fmt=fmt)

    def close(self) -> None:
        with self._lock, self._read_lock:
            for client in (self._client, self._read_client):
                if client is not None:
                    client.close()
            self._client = self._read_client = None
