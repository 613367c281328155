"""The store's time-travel and replay reads: the map and the robots at an instant, poses
(raw and downsampled), chunk writes, the timeline, chunk contents and the latest map
metadata, all on the read client (conflicts: `conflict_reads`).

`ClickHouseTimeTravel` (the TimeTravelReader role) holds the connection (reads use only
valid snapshots: `ClickHouseConnection.valid_before`), the conflict reads (the timeline
counts conflicts) and the track reads (`robot_track`, `track_buckets`); it also depends on
`pose_schema` for the keyframe columns, never on the store's other roles.
"""

from __future__ import annotations

from collections.abc import Sequence

import msgspec

from mapservice.adapters.clickhouse.conflict_reads import ClickHouseConflictReads
from mapservice.adapters.clickhouse.connection import (
    FINAL_SETTINGS,
    POSE_READ_COLUMNS,
    ClickHouseConnection,
)
from mapservice.adapters.clickhouse.pose_schema import KEYFRAME_MS, POSE_COLUMNS
from mapservice.adapters.clickhouse.track_reads import ClickHouseTrackReads
from mapservice.core.events import MapMetaSet
from mapservice.core.ports import ChunkRow, ChunkState, PoseRow, TimelineBucket, TrackBucket
from mapservice.core.timetravel import timeline_buckets


class ClickHouseTimeTravel:
    """Time travel and replay."""

    def __init__(
        self,
        connection: ClickHouseConnection,
        conflicts: ClickHouseConflictReads,
        tracks: ClickHouseTrackReads,
    ) -> None:
        self.connection = connection
        self._conflicts = conflicts
        self._tracks = tracks

    def robot_track(
        self, robot_id: str, from_ms: int, to_ms: int, step_ms: int = 0, limit: int = 100_000
    ) -> list[PoseRow]:
        return self._tracks.robot_track(robot_id, from_ms, to_ms, step_ms, limit)

    def track_buckets(
        self, robot_id: str, from_ms: int, to_ms: int, bucket_ms: int
    ) -> list[TrackBucket]:
        return self._tracks.track_buckets(robot_id, from_ms, to_ms, bucket_ms)

    def poses(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 100_000
    ) -> list[PoseRow]:
        # PREWHERE on sorting-key columns only: duplicates of one identity pass or fail
        # together, so FINAL still sees all of them; the other columns are read only for
        # granules holding rows of the window.
        where = (
            "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        )
        params: dict = {"f": from_ms, "t": to_ms, "n": limit}
        if robot_id is not None:
            where += " AND robot_id = {r:String}"
            params["r"] = robot_id
        return self.connection.pose_query(
            f"SELECT {POSE_READ_COLUMNS} FROM {self.connection.database}.poses FINAL PREWHERE {where} "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            params,
        )

    def poses_downsampled(
        self,
        from_ms: int,
        to_ms: int,
        step_ms: int,
        robot_id: str | None = None,
        limit: int = 100_000,
    ) -> list[PoseRow]:
        """Per robot and step bucket [from + k*step, from + (k+1)*step), its first pose in
        from_ms <= event time < to_ms; ordered by time then robot, like poses()."""
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        where = (
            "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        )
        params: dict = {"f": from_ms, "t": to_ms, "s": step_ms, "n": limit}
        if robot_id is not None:
            where += " AND robot_id = {r:String}"
            params["r"] = robot_id
        aligned = from_ms % KEYFRAME_MS == 0 and step_ms % KEYFRAME_MS == 0
        if aligned:
            # pose_keyframes is sorted by (cell, robot_id) (schema v9): read in that order,
            # the first keyframe of each (robot, step) is the first one met, and reading
            # stops at the LIMIT. (cell, ts, robot_id) is the (ts, robot_id) order.
            robot = " AND robot_id = {r:String}" if robot_id is not None else ""
            return self.connection.pose_query(
                f"SELECT {POSE_READ_COLUMNS} FROM {self.connection.database}.pose_keyframes FINAL "
                "PREWHERE cell >= fromUnixTimestamp64Milli({f:Int64}) "
                f"AND cell < fromUnixTimestamp64Milli({{t:Int64}}){robot} "
                "WHERE ts < fromUnixTimestamp64Milli({t:Int64}) ORDER BY cell, ts, robot_id "
                # A step of one minute is one keyframe per robot already (FINAL).
                + (
                    ""
                    if step_ms == KEYFRAME_MS
                    else "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64}) "
                )
                + f"LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
                params,
            )
        if step_ms >= 10 * KEYFRAME_MS:
            return self.connection.pose_query(
                self._keyframe_sql(_step_heads(from_ms, to_ms, step_ms), robot_id), params
            )
        return self.connection.pose_query(
            f"SELECT {POSE_READ_COLUMNS} FROM (SELECT * FROM {self.connection.database}.poses FINAL WHERE {where} "
            "ORDER BY robot_id, ts "
            "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            params,
        )

    def _keyframe_sql(self, heads: list[tuple[int, int]] | None, robot_id: str | None) -> str:
        """poses_downsampled from the per-minute keyframes (schema v4), exactly.

        A step [b, b + step) is a head [b, next whole minute), then minutes starting in it.
        Its first pose is either in the head, or the first pose of the first of those
        minutes holding one in the step, i.e. that minute's keyframe (a minute cut by the
        step's end counts only if its keyframe is before the end). So the candidates are
        the keyframes in the window plus every pose in the heads, read from `poses`: none
        when `from` and the step are whole minutes (`heads` None), a minute per step at
        most otherwise (steps of 10 min or more). The heads are given as explicit time
        ranges, so the primary key reads only their granules (a condition computed from
        `ts` alone would read the time column of the whole window to find them).
        """
        db = self.connection.database
        robot = " AND robot_id = {r:String}" if robot_id is not None else ""
        window = (
            "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        )
        candidates = (
            f"SELECT {POSE_COLUMNS} FROM {db}.pose_keyframes FINAL "
            "PREWHERE cell >= toStartOfMinute(fromUnixTimestamp64Milli({f:Int64})) "
            f"AND cell < fromUnixTimestamp64Milli({{t:Int64}}){robot} WHERE {window}"
        )
        if heads:
            ranges = " OR ".join(
                f"(ts >= fromUnixTimestamp64Milli({lo}) AND ts < fromUnixTimestamp64Milli({hi}))"
                for lo, hi in heads
            )
            candidates += (
                f" UNION ALL SELECT {POSE_COLUMNS} FROM {db}.poses FINAL PREWHERE ({ranges}){robot}"
            )
        return (
            f"SELECT {POSE_READ_COLUMNS} FROM (SELECT * FROM ({candidates}) ORDER BY robot_id, ts "
            "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {FINAL_SETTINGS}"
        )

    def map_at(self, at_ms: int) -> list[ChunkState]:
        """Every chunk's winning write at or before `at_ms` (nearest snapshot + events).

        One statement: the nearest snapshot's time is a scalar subquery (ClickHouse folds
        it to a constant before choosing granules). Without a snapshot it is the epoch, so
        the snapshot side is empty and every event <= `at_ms` is folded.
        """
        db = self.connection.database
        with self.connection.reader() as c:
            rows = c.query(
                f"WITH (SELECT max(snap_ts) FROM {db}.snapshot_log "
                "WHERE snap_ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"AND snap_ts < {self.connection.valid_before()}) AS snap "
                "SELECT row, col, toUnixTimestamp64Milli(max(ts)), argMax(robot_id, (ts, robot_id)), "
                "lower(hex(argMax(content_hash, (ts, robot_id)))) "
                f"FROM (SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots "
                "WHERE snap_ts = snap UNION ALL "
                f"SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events "
                "WHERE ts > snap AND ts <= fromUnixTimestamp64Milli({t:Int64})) "
                "GROUP BY row, col ORDER BY row, col",
                parameters={"t": at_ms},
            ).result_rows
        return [ChunkState(*r) for r in rows]

    def robots_at(
        self, at_ms: int, after: str | None = None, limit: int | None = None
    ) -> list[PoseRow]:
        """Each robot's latest pose at or before `at_ms` (nearest snapshot + events).

        One statement in two passes over `poses`: the first finds each robot's latest time,
        reading only (robot_id, ts) of the poses in (snapshot, at_ms] plus the snapshot's
        time of each robot's last pose (robots silent since); the second reads the other
        columns only for the granules holding those (robot, ts) keys, which the primary key
        finds (`(ts, robot_id) in set`). Without a valid snapshot the first pass reads every
        pose <= at_ms (two columns), still exact.

        A page (`after`, `limit`) is cut in the first pass, so a fleet of 100,000 robot ids
        sends one page's rows, not every robot's, and the second pass reads only the page's.
        """
        db = self.connection.database
        params: dict = {"t": at_ms}
        page = ""
        if after is not None:
            page, params["after"] = " AND robot_id > {after:String}", after
        cut = ""
        if limit is not None:
            cut, params["n"] = " ORDER BY robot_id LIMIT {n:UInt32}", limit
        latest = (
            "(SELECT robot_id, max(ts) FROM ("
            f"SELECT robot_id, ts FROM {db}.poses "
            "PREWHERE ts > snap AND ts <= fromUnixTimestamp64Milli({t:Int64})"
            + page
            + " UNION ALL "
            # max(ts): a rebuilt snapshot may still hold its older rows until merged.
            f"SELECT robot_id, ts FROM {db}.robot_snapshots WHERE snap_ts = snap{page}) "
            f"GROUP BY robot_id{cut})"
        )
        return self.connection.pose_query(
            f"WITH (SELECT max(snap_ts) FROM {db}.snapshot_log "
            "WHERE snap_ts <= fromUnixTimestamp64Milli({t:Int64}) "
            f"AND snap_ts < {self.connection.valid_before()}) AS snap "
            f"SELECT {POSE_READ_COLUMNS} FROM (SELECT * FROM {db}.poses FINAL "
            f"PREWHERE (robot_id, ts) IN {latest} UNION ALL "
            # A robot silent since before the retention: its last pose, carried (retention.py).
            f"SELECT * FROM {db}.carried_poses FINAL WHERE (robot_id, ts) IN {latest}) "
            f"ORDER BY robot_id LIMIT 1 BY robot_id {FINAL_SETTINGS}",
            params,
        )

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        # PREWHERE on the sorting key's `ts`: as in poses(), FINAL sees every duplicate.
        rows = self.connection.rows(
            f"SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.connection.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_id LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def chunk_events_compacted(
        self, from_ms: int, to_ms: int, step_ms: int, limit: int = 100_000
    ) -> list[ChunkRow]:
        """Per chunk and absolute bucket [k*step, (k+1)*step) of from_ms <= event time <
        to_ms, only the bucket's winning write: the greatest (event time, robot id), the
        rule of map_at. Computed at query time from `chunk_events`, no cache.

        Two passes: each (chunk, bucket)'s latest time from the sorting-key columns alone
        (no FINAL needed: a duplicate has the same time), then the writes at those
        (row, col, ts) keys, FINAL (of two rows with one identity, the one chunk_events()
        returns), the greatest robot id winning a tie. One pass of argMax over (ts,
        robot_id) tuples took 2-4 s for a day of 200 robots (3.5 M writes), this ~0.7 s.
        """
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        db = self.connection.database
        window = (
            "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        )
        rows = self.connection.rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts) AS t, max(robot_id) AS robot, "
            "lower(hex(argMax(content_hash, robot_id))), argMax(recv_lag_ms, robot_id) "
            f"FROM {db}.chunk_events FINAL PREWHERE {window} AND (row, col, ts) IN ("
            f"SELECT row, col, max(ts) FROM {db}.chunk_events PREWHERE {window} "
            "GROUP BY row, col, intDiv(toUnixTimestamp64Milli(ts), {s:Int64})) "
            f"GROUP BY row, col, ts ORDER BY t, row, col, robot LIMIT {{n:UInt32}} {FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "s": step_ms, "n": limit},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def timeline(self, from_ms: int, to_ms: int, buckets: int) -> list[TimelineBucket]:
        bucket_ms, starts = timeline_buckets(from_ms, to_ms, buckets)
        if not starts:
            return []
        chunks = self._timeline_chunks(from_ms, to_ms, bucket_ms)
        robots = self._timeline_robots(from_ms, to_ms, bucket_ms)
        conflicts = self._conflicts.conflict_counts(from_ms, to_ms, bucket_ms)
        return [
            TimelineBucket(start, chunks.get(k, 0), conflicts.get(start, 0), robots.get(k, 0))
            for k, start in enumerate(starts)
        ]

    def _timeline_chunks(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        """Chunk changes per bucket (k: the bucket's index), as `count() FROM chunk_events
        FINAL` gives them.

        Seconds before the newest valid snapshot come from `chunk_seconds` (deduplicated,
        written with the snapshots): a second inside the window and inside one bucket
        counts its length; a second cut by a bucket edge or the window's ends counts its
        millisecond offsets one by one. Events from that snapshot on (and all of them
        without one) are counted from chunk_events FINAL, as before.
        """
        db = self.connection.database
        params = {
            "f": from_ms,
            "t": to_ms,
            "b": bucket_ms,
            "f0": from_ms // 1000,
            "t1": -(-to_ms // 1000),
        }
        cov = (
            f"(SELECT toDateTime(max(snap_ts)) FROM {db}.snapshot_log "
            f"WHERE snap_ts < {self.connection.valid_before()})"
        )
        seconds = (
            f"{db}.chunk_seconds FINAL PREWHERE second >= toDateTime({{f0:Int64}}) "
            "AND second < least(cov, toDateTime({t1:Int64}))"
        )
        if from_ms % 1000 == 0 and to_ms % 1000 == 0 and bucket_ms % 1000 == 0:
            covered = (
                f"SELECT intDiv(toUnixTimestamp(second) * 1000 - {{f:Int64}}, {{b:Int64}}) AS k, "
                f"sum(changes) AS n FROM {seconds} GROUP BY k"
            )
        else:
            s = "toInt64(toUnixTimestamp(second)) * 1000"
            whole = (
                f"{s} >= {{f:Int64}} AND {s} + 1000 <= {{t:Int64}} AND "
                f"intDiv({s} - {{f:Int64}}, {{b:Int64}}) = intDiv({s} + 999 - {{f:Int64}}, {{b:Int64}})"
            )
            covered = (
                "SELECT tupleElement(kn, 1) AS k, sum(tupleElement(kn, 2)) AS n FROM ("
                f"SELECT arrayJoin(if({whole}, [(intDiv({s} - {{f:Int64}}, {{b:Int64}}), length(offsets))], "
                f"arrayMap(o -> (intDiv({s} + o - {{f:Int64}}, {{b:Int64}}), toUInt64(1)), "
                f"arrayFilter(o -> {s} + o >= {{f:Int64}} AND {s} + o < {{t:Int64}}, offsets)))) AS kn "
                f"FROM {seconds}) GROUP BY k"
            )
        rows = self.connection.rows(
            f"WITH {cov} AS cov SELECT k, sum(n) FROM ({covered} UNION ALL "
            f"SELECT intDiv(toUnixTimestamp64Milli(ts) - {{f:Int64}}, {{b:Int64}}) AS k, count() AS n "
            f"FROM {db}.chunk_events FINAL PREWHERE ts >= greatest(fromUnixTimestamp64Milli({{f:Int64}}), cov) "
            "AND ts < fromUnixTimestamp64Milli({t:Int64}) GROUP BY k) GROUP BY k "
            f"{FINAL_SETTINGS}",
            params,
        )
        return {int(k): int(n) for k, n in rows}

    def _timeline_robots(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        """Robots with a pose per bucket (k: the bucket's index).

        Buckets of a minute or more: a minute inside the window lies in at most two
        buckets, so a robot has a pose in a bucket iff its first or its last pose of one
        such minute lies there (`pose_minutes`; with whole-minute buckets the first alone
        tells); the same holds for ten minutes and buckets of ten minutes or more
        (`pose_ten_minutes`, whose cells cut by the window's ends are read per minute).
        The minutes the window's ends cut are read from `poses`, as are shorter buckets.
        A duplicate pose names the same robot: no FINAL needed anywhere.
        """
        db = self.connection.database
        params = {"f": from_ms, "t": to_ms, "b": bucket_ms}
        bucket = "intDiv(toUnixTimestamp64Milli({x}) - {{f:Int64}}, {{b:Int64}})"
        parts = []
        for table, lo, hi in _robot_cells(from_ms, to_ms, bucket_ms):
            if table is None:
                parts.append(
                    f"SELECT robot_id, {bucket.format(x='ts')} AS k FROM {db}.poses "
                    f"PREWHERE ts >= fromUnixTimestamp64Milli({lo}) "
                    f"AND ts < fromUnixTimestamp64Milli({hi})"
                )
                continue
            size = _CELL_MS[table]
            aligned = from_ms % size == 0 and bucket_ms % size == 0  # a cell in one bucket
            times = "[first_ts]" if aligned else "[first_ts, last_ts]"
            parts.append(
                f"SELECT robot_id, {bucket.format(x='x')} AS k FROM {db}.{table} "
                f"ARRAY JOIN {times} AS x WHERE cell >= fromUnixTimestamp64Milli({lo}) "
                f"AND cell < fromUnixTimestamp64Milli({hi})"
            )
        rows = self.connection.rows(
            f"SELECT k, uniqExact(robot_id) FROM ({' UNION ALL '.join(parts)}) GROUP BY k", params
        )
        return {int(k): int(n) for k, n in rows}

    def robot_known(self, robot_id: str) -> bool:
        # pose_keyframes: a row per robot and minute, robot ids as LowCardinality (a part
        # without the robot in its dictionary is skipped), not a scan of `poses`.
        return bool(
            self.connection.rows(
                f"SELECT 1 FROM {self.connection.database}.pose_keyframes WHERE robot_id = {{r:String}} LIMIT 1",
                {"r": robot_id},
            )
        )

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        rows = self.connection.rows(
            f"SELECT width, height, zlib_pixels FROM {self.connection.database}.chunk_contents "
            "WHERE content_hash = unhex({h:String}) LIMIT 1",
            {"h": content_hash.hex()},
            # As bytes: read as text, zlib data that is not UTF-8 would come back as hex.
            column_formats={"zlib_pixels": "bytes"},
        )
        if not rows:
            return None
        w, h, data = rows[0]
        return w, h, bytes(data)

    def chunk_contents(self, hashes: Sequence[bytes]) -> dict[bytes, tuple[int, int, bytes]]:
        """Many content hashes at once: hash -> (width, height, zlib pixels)."""
        if not hashes:
            return {}
        rows = self.connection.rows(
            f"SELECT content_hash, any(width), any(height), any(zlib_pixels) "
            f"FROM {self.connection.database}.chunk_contents WHERE content_hash IN "
            "(SELECT arrayJoin(arrayMap(h -> toFixedString(unhex(h), 16), {hs:Array(String)}))) "
            "GROUP BY content_hash",
            {"hs": [h.hex() for h in set(hashes)]},
            column_formats={"content_hash": "bytes", "any(zlib_pixels)": "bytes"},
        )
        return {bytes(h): (w, ht, bytes(d)) for h, w, ht, d in rows}

    def latest_meta(self) -> MapMetaSet | None:
        rows = self.connection.rows(
            f"SELECT meta FROM {self.connection.database}.map_meta FINAL ORDER BY ts DESC LIMIT 1",
            {},
        )
        if not rows:
            return None
        doc = msgspec.json.decode(rows[0][0])
        return MapMetaSet.from_2019(doc)


def _step_heads(from_ms: int, to_ms: int, step_ms: int) -> list[tuple[int, int]]:
    """Each step's head [b, the next whole minute), within the step and the window: the
    poses a keyframe read cannot stand for (empty heads left out)."""
    heads = []
    for b in range(from_ms, to_ms, step_ms):
        end = min(-(-b // KEYFRAME_MS) * KEYFRAME_MS, b + step_ms, to_ms)
        if end > b:
            heads.append((int(b), int(end)))
    return heads


_CELL_MS = {"pose_ten_minutes": 600_000, "pose_minutes": KEYFRAME_MS}


def _robot_cells(
    lo: int, hi: int, bucket_ms: int, levels: tuple[str, ...] = ("pose_ten_minutes", "pose_minutes")
) -> list[tuple[str | None, int, int]]:
    """[lo, hi) as (table, start, end) pieces: whole cells of the coarsest level not
    longer than a bucket, the rest of each end in finer levels, and `poses` (None) for
    what no whole minute covers."""
    if hi <= lo:
        return []
    for i, table in enumerate(levels):
        size = _CELL_MS[table]
        a, b = -(-lo // size) * size, hi // size * size
        if bucket_ms >= size and b > a:
            rest = levels[i + 1 :]
            return (
                _robot_cells(lo, a, bucket_ms, rest)
                + [(table, a, b)]
                + _robot_cells(b, hi, bucket_ms, rest)
            )
    return [(None, lo, hi)]
