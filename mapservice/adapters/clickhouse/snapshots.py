"""The store's snapshots: building them (one at a time or in bulk runs), finding the newest
and the nearest valid one, and repairing those a late event made wrong. Each build also
writes `chunk_seconds` (schema v9), `chunk_bursts` (v18) and `heatmap_cells` (v21) for the
time before its snapshot, so those rows are valid exactly where the snapshots are.

`ClickHouseSnapshots` (the SnapshotKeeper role) runs on the writer client of the
`connection.ClickHouseConnection` it holds and depends on nothing else of the store but
the schema modules (the chunk_seconds, chunk_bursts and heatmap_cells queries). It also knows the newest
snapshot: the writer (a late event notes a repair) and the retention (its anchor) are
handed the same instance.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from mapservice.adapters.clickhouse import burst_schema, heatmap_schema
from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, ClickHouseConnection
from mapservice.adapters.clickhouse.pose_schema import CHUNK_SECONDS_SELECT
from mapservice.core.heatmaps import HeatmapRule

NO_SNAPSHOT_RECHECK_S = 5.0


class ClickHouseSnapshots:
    """Snapshots of the map and the robots every `snapshot_every_ms`."""

    def __init__(
        self,
        connection: ClickHouseConnection,
        snapshot_every_ms: int = 600_000,
        heatmap_rule: HeatmapRule | None = None,
    ) -> None:
        self.connection = connection
        self.snapshot_every_ms = snapshot_every_ms
        self.heatmap_rule = heatmap_rule or HeatmapRule()
        self._last_snapshot_ms: int | None = None  # newest snapshot built, once known
        self._no_snapshot_until = 0.0  # monotonic time until which "no snapshot yet" holds

    # --- snapshots ------------------------------------------------------------------
    # A snapshot at S holds, per chunk, the winning write with event time <= S and, per
    # robot, the time of its latest pose <= S. Snapshot S is built from snapshot S - every
    # plus the events in (S - every, S], so building is cheap and reading the state at T
    # costs one snapshot plus at most `every` of events, however old T is.

    def newest_snapshot(self) -> int | None:
        """The newest snapshot's time, or None before the first (under the writer's lock)."""
        # Every batch asks; until the first snapshot exists, "none" is asked again at
        # most every few seconds instead of once per batch (~4 ms each on chDB).
        if self._last_snapshot_ms is None and time.monotonic() >= self._no_snapshot_until:
            rows = self.connection.client.query(
                f"SELECT toUnixTimestamp64Milli(max(snap_ts)), count() "
                f"FROM {self.connection.database}.snapshot_log"
            ).result_rows
            if rows and rows[0][1]:
                self._last_snapshot_ms = rows[0][0]
            else:
                self._no_snapshot_until = time.monotonic() + NO_SNAPSHOT_RECHECK_S
        return self._last_snapshot_ms

    def _build_one(self, snap_ms: int, prev_ms: int | None) -> None:
        db = self.connection.database
        params = {"s": snap_ms, "p": prev_ms if prev_ms is not None else -1}
        # prev == snap refolds a snapshot: its own rows plus every event up to it (a late
        # event older than the oldest snapshot, whose base is gone with the retention).
        since = (
            "ts > fromUnixTimestamp64Milli({p:Int64}) AND "
            if prev_ms is not None and prev_ms != snap_ms
            else ""
        )
        prev_map = (
            f"SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots FINAL "
            "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) UNION ALL "
            if prev_ms is not None
            else ""
        )
        prev_robots = (
            f"SELECT robot_id, ts FROM {db}.robot_snapshots FINAL "
            "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) UNION ALL "
            if prev_ms is not None
            else ""
        )
        c = self.connection.client
        c.command(
            f"INSERT INTO {db}.map_snapshots (snap_ts, row, col, ts, robot_id, content_hash, built) "
            "SELECT fromUnixTimestamp64Milli({s:Int64}), row, col, max(ts), "
            "argMax(robot_id, (ts, robot_id)), argMax(content_hash, (ts, robot_id)), now64(3) "
            f"FROM ({prev_map}SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events "
            f"WHERE {since}ts <= fromUnixTimestamp64Milli({{s:Int64}})) GROUP BY row, col",
            parameters=params,
        )
        c.command(
            f"INSERT INTO {db}.robot_snapshots (snap_ts, robot_id, ts, built) "
            "SELECT fromUnixTimestamp64Milli({s:Int64}), robot_id, max(ts), now64(3) "
            f"FROM ({prev_robots}SELECT robot_id, ts FROM {db}.poses "
            f"WHERE {since}ts <= fromUnixTimestamp64Milli({{s:Int64}})) GROUP BY robot_id",
            parameters=params,
        )
        self._write_chunk_seconds(prev_ms, snap_ms)
        self._write_chunk_bursts(prev_ms, snap_ms)
        self._write_heatmap_cells(prev_ms, snap_ms)
        c.command(
            f"INSERT INTO {db}.snapshot_log (snap_ts, built, chunks, robots) "
            "SELECT fromUnixTimestamp64Milli({s:Int64}), now64(3), "
            f"(SELECT count() FROM {db}.map_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({{s:Int64}})), "
            f"(SELECT count() FROM {db}.robot_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({{s:Int64}}))",
            parameters=params,
        )

    def _write_chunk_seconds(self, prev_ms: int | None, snap_ms: int) -> None:
        """chunk_seconds for the whole seconds in [prev, snap) (all before snap without a
        previous snapshot), from chunk_events FINAL: the same rows whichever snapshots
        are built together (one by one, in bulk runs, in repairs)."""
        since = "ts >= fromUnixTimestamp64Milli({p:Int64}) AND " if prev_ms is not None else ""
        self.connection.client.command(
            f"INSERT INTO {self.connection.database}.chunk_seconds (second, offsets, built) "
            f"{CHUNK_SECONDS_SELECT} FROM {self.connection.database}.chunk_events FINAL "
            f"PREWHERE {since}ts < fromUnixTimestamp64Milli({{s:Int64}}) GROUP BY second "
            f"{FINAL_SETTINGS}",
            parameters={"p": (prev_ms or 0) // 1000 * 1000, "s": snap_ms // 1000 * 1000},
        )

    def _write_chunk_bursts(self, prev_ms: int | None, snap_ms: int) -> None:
        """chunk_bursts for the whole buckets in [prev, snap) (all before snap without a
        previous snapshot): consecutive builds tile the buckets, whichever way they run."""
        b = burst_schema.BUCKET_S * 1000
        since = "ts >= fromUnixTimestamp64Milli({p:Int64}) AND " if prev_ms is not None else ""
        self.connection.client.command(
            f"INSERT INTO {self.connection.database}.{burst_schema.TABLE} (bucket, robot_id, writes, built) "
            f"{burst_schema.BURSTS_SELECT} FROM {self.connection.database}.chunk_events FINAL "
            f"PREWHERE {since}ts < fromUnixTimestamp64Milli({{s:Int64}}) {burst_schema.BURSTS_KEPT} "
            f"{FINAL_SETTINGS}",
            parameters={"p": (prev_ms or 0) // b * b, "s": snap_ms // b * b},
        )

    def _write_heatmap_cells(self, prev_ms: int | None, snap_ms: int) -> None:
        """heatmap_cells for the whole buckets in [prev, snap) (all before snap without a
        previous snapshot), from poses FINAL: consecutive builds tile the buckets."""
        b = heatmap_schema.BUCKET_MS
        lo, hi = (prev_ms or 0) // b * b, snap_ms // b * b
        if lo >= hi:
            return  # no whole bucket ended since the previous build
        self.connection.client.command(
            heatmap_schema.buckets_insert(
                self.connection.database, "{p:Int64}", "{s:Int64}", self.heatmap_rule
            )
            + f" {FINAL_SETTINGS}",
            parameters={"p": lo, "s": hi},
        )

    def note_repair(self, from_ms: int) -> None:
        """Notes that the snapshots from `from_ms` on are wrong (a late event): reads skip
        them until `repair_snapshots` rebuilds them (under the writer's lock)."""
        self.connection.insert(
            "snapshot_repairs", [[from_ms, time.time_ns() // 1_000_000]], ["from_ts", "noted"]
        )

    def repair_snapshots(self, max_snapshots: int = 144) -> int:
        """Rebuilds at most `max_snapshots` of the snapshots a late event invalidated,
        oldest first, in one bulk statement per table; returns how many. The snapshot
        timer calls it until nothing is pending, so a late event costs the consumer no
        time and the repair is spread over ticks."""
        db, every = self.connection.database, self.snapshot_every_ms
        with self.connection.lock:
            rows = self.connection.client.query(
                f"SELECT toUnixTimestamp64Milli(min(from_ts)), count(), "
                f"toUnixTimestamp64Milli(max(noted)) FROM {db}.snapshot_repairs"
            ).result_rows
            if not rows or not rows[0][1]:
                return 0
            from_ms, _, noted_ms = rows[0]
            newest = self.newest_snapshot()
            first = -(-from_ms // every) * every  # the first snapshot that can contain from_ms
            # The oldest snapshot carries the floor from before the retention (whose events
            # are gone): never rebuilt from events alone, it is the base of every rebuild.
            ((oldest, known),) = self.connection.client.query(
                f"SELECT toUnixTimestamp64Milli(min(snap_ts)), count() FROM {db}.snapshot_log"
            ).result_rows
            refolded = 0
            if known and first <= oldest:
                self._build_one(oldest, oldest)
                first, refolded = oldest + every, 1
            if newest is None or first > newest:  # nothing (more) to rebuild
                self.connection.client.command(
                    f"DELETE FROM {db}.snapshot_repairs WHERE noted <= "
                    "fromUnixTimestamp64Milli({n:Int64})",
                    parameters={"n": noted_ms},
                )
                return refolded
            last = min(newest, first + (max_snapshots - 1) * every)
            prev = first - every
            self._build_run(first, last, prev if self._has_snapshot(prev) else None)
            # Done up to `last`: what was noted before this step now starts after it (a
            # late event noted meanwhile keeps its own, earlier row).
            if last < newest:
                self.connection.insert(
                    "snapshot_repairs", [[last + 1, noted_ms]], ["from_ts", "noted"]
                )
            self.connection.client.command(
                f"DELETE FROM {db}.snapshot_repairs WHERE noted <= fromUnixTimestamp64Milli({{n:Int64}}) "
                "AND from_ts <= fromUnixTimestamp64Milli({l:Int64})",
                parameters={"n": noted_ms, "l": last},
            )
            return (last - first) // every + 1 + refolded

    def _has_snapshot(self, snap_ms: int) -> bool:
        return bool(
            self.connection.client.query(
                f"SELECT count() FROM {self.connection.database}.snapshot_log WHERE snap_ts = "
                "fromUnixTimestamp64Milli({s:Int64})",
                parameters={"s": snap_ms},
            ).result_rows[0][0]
        )

    def build_snapshots(self, up_to_ms: int) -> int:
        """Builds every grid snapshot up to `up_to_ms` not built yet; returns how many."""
        every = self.snapshot_every_ms
        with self.connection.lock:
            last = self.newest_snapshot()
            if last is None:
                rows = self.connection.client.query(
                    "SELECT toUnixTimestamp64Milli(min(ts)), count() FROM ("
                    f"SELECT ts FROM {self.connection.database}.chunk_events UNION ALL "
                    f"SELECT ts FROM {self.connection.database}.poses)"
                ).result_rows
                if not rows[0][1]:
                    return 0
                # The first snapshot folds everything before it; each later one one interval.
                oldest = max(rows[0][0], up_to_ms - self.connection.retention_days * 86_400_000)
                first = oldest // every * every
                snaps = list(range(first, up_to_ms + 1, every))
                prev = None
            else:
                snaps = list(range(last + every, up_to_ms + 1, every))
                prev = last
            for snap in snaps:
                self._build_one(snap, prev)
                prev = snap
                self._last_snapshot_ms = snap
            return len(snaps)

    def _due_snapshots(self, up_to_ms: int) -> tuple[list[int], int | None]:
        """The snapshots build_snapshots(up_to_ms) would build, and the one before them."""
        every = self.snapshot_every_ms
        last = self.newest_snapshot()
        if last is not None:
            return list(range(last + every, up_to_ms + 1, every)), last
        rows = self.connection.client.query(
            "SELECT toUnixTimestamp64Milli(min(ts)), count() FROM ("
            f"SELECT ts FROM {self.connection.database}.chunk_events UNION ALL "
            f"SELECT ts FROM {self.connection.database}.poses)"
        ).result_rows
        if not rows[0][1]:
            return [], None
        oldest = max(rows[0][0], up_to_ms - self.connection.retention_days * 86_400_000)
        return list(range(oldest // every * every, up_to_ms + 1, every)), None

    def build_snapshots_bulk(
        self,
        up_to_ms: int,
        per_query: int = 144,
        on_progress: Callable[[int, int], None] | None = None,
    ) -> int:
        """build_snapshots(up_to_ms), `per_query` snapshots per statement: the same rows.

        For a run of snapshots S1 < ... < Sn following snapshot P (or none): each write
        with P < t <= Sn (or any t <= Sn without P) falls in the bucket of the first
        snapshot at or after it (S1 for everything older), P's rows in bucket P; the
        winners per bucket and chunk (robot) are then carried forward to every later
        snapshot with an ASOF JOIN. That is what the chain of `_build_one` computes, one
        statement per table and run instead of three per snapshot.
        """
        with self.connection.lock:
            snaps, prev = self._due_snapshots(up_to_ms)
            for i in range(0, len(snaps), per_query):
                run = snaps[i : i + per_query]
                self._build_run(run[0], run[-1], prev)
                prev = run[-1]
                self._last_snapshot_ms = prev
                if on_progress is not None:
                    on_progress(i + len(run), len(snaps))
            return len(snaps)

    def _build_run(self, first_ms: int, last_ms: int, prev_ms: int | None) -> None:
        db, every = self.connection.database, self.snapshot_every_ms
        params = {
            "a": first_ms,
            "b": last_ms,
            "e": every,
            "p": prev_ms if prev_ms is not None else -1,
        }
        since = "ts > fromUnixTimestamp64Milli({p:Int64}) AND " if prev_ms is not None else ""
        bucket = (
            "greatest({a:Int64}, intDiv(toUnixTimestamp64Milli(ts) + {e:Int64} - 1, "
            "{e:Int64}) * {e:Int64})"
        )
        snap_times = "arrayJoin(range({a:Int64}, {b:Int64} + 1, {e:Int64}))"
        prev_map = (
            f"SELECT {{p:Int64}} AS bucket, row, col, ts, robot_id, content_hash "
            f"FROM {db}.map_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({{p:Int64}}) "
            "UNION ALL "
            if prev_ms is not None
            else ""
        )
        prev_robots = (
            f"SELECT {{p:Int64}} AS bucket, robot_id, ts FROM {db}.robot_snapshots FINAL "
            "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) UNION ALL "
            if prev_ms is not None
            else ""
        )
        c = self.connection.client
        c.command(
            f"INSERT INTO {db}.map_snapshots (snap_ts, row, col, ts, robot_id, content_hash, built) "
            "WITH w AS (SELECT bucket, row, col, max(ts) AS win_ts, "
            "argMax(robot_id, (ts, robot_id)) AS win_robot, "
            "argMax(content_hash, (ts, robot_id)) AS win_hash "
            f"FROM ({prev_map}SELECT {bucket} AS bucket, row, col, ts, robot_id, content_hash "
            f"FROM {db}.chunk_events WHERE {since}ts <= fromUnixTimestamp64Milli({{b:Int64}})) "
            "GROUP BY bucket, row, col) "
            "SELECT fromUnixTimestamp64Milli(g.snap), g.row, g.col, w.win_ts, w.win_robot, "
            "w.win_hash, now64(3) "
            f"FROM (SELECT {snap_times} AS snap, row, col FROM (SELECT DISTINCT row, col FROM w)) AS g "
            "ASOF JOIN w ON g.row = w.row AND g.col = w.col AND g.snap >= w.bucket",
            parameters=params,
        )
        c.command(
            f"INSERT INTO {db}.robot_snapshots (snap_ts, robot_id, ts, built) "
            "WITH w AS (SELECT bucket, robot_id, max(ts) AS win_ts "
            f"FROM ({prev_robots}SELECT {bucket} AS bucket, robot_id, ts FROM {db}.poses "
            f"WHERE {since}ts <= fromUnixTimestamp64Milli({{b:Int64}})) GROUP BY bucket, robot_id) "
            "SELECT fromUnixTimestamp64Milli(g.snap), g.robot_id, w.win_ts, now64(3) "
            f"FROM (SELECT {snap_times} AS snap, robot_id FROM (SELECT DISTINCT robot_id FROM w)) AS g "
            "ASOF JOIN w ON g.robot_id = w.robot_id AND g.snap >= w.bucket",
            parameters=params,
        )
        self._write_chunk_seconds(prev_ms, last_ms)
        self._write_chunk_bursts(prev_ms, last_ms)
        self._write_heatmap_cells(prev_ms, last_ms)
        window = (
            "snap_ts >= fromUnixTimestamp64Milli({a:Int64}) AND "
            "snap_ts <= fromUnixTimestamp64Milli({b:Int64})"
        )
        c.command(
            f"INSERT INTO {db}.snapshot_log (snap_ts, built, chunks, robots) "
            "SELECT fromUnixTimestamp64Milli(g.snap), now64(3), m.n, r.n "
            f"FROM (SELECT {snap_times} AS snap) AS g "
            "LEFT JOIN (SELECT toUnixTimestamp64Milli(snap_ts) AS snap, count() AS n "
            f"FROM {db}.map_snapshots FINAL WHERE {window} GROUP BY snap_ts) AS m ON g.snap = m.snap "
            "LEFT JOIN (SELECT toUnixTimestamp64Milli(snap_ts) AS snap, count() AS n "
            f"FROM {db}.robot_snapshots FINAL WHERE {window} GROUP BY snap_ts) AS r ON g.snap = r.snap",
            parameters=params,
        )
