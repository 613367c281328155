"""The store's time-travel and replay reads: the map and the robots at an instant, poses
(raw and downsampled), chunk writes, the timeline, conflicts, chunk contents and the latest
map metadata, all on the read client.

`ReadsMixin` builds on `snapshots.SnapshotsMixin` (reads use only valid snapshots) and so
on `connection`; it also depends on `schema` for the keyframe columns, never on the
store's other mixins.
"""

from __future__ import annotations

from collections.abc import Sequence

import msgspec

from mapservice.core.events import MapMetaSet
from mapservice.core.ports import ChunkRow, ChunkState, ConflictRow, PoseRow, TimelineBucket
from mapservice.core.timetravel import timeline_buckets
from mapservice.adapters.clickhouse.connection import _FINAL_SETTINGS, _POSE_COLUMNS, _pose_rows
from mapservice.adapters.clickhouse.schema import KEYFRAME_MS, POSE_COLUMNS
from mapservice.adapters.clickhouse.snapshots import SnapshotsMixin


class ReadsMixin(SnapshotsMixin):
    """Time travel and replay."""

    # --- reads ----------------------------------------------------------------------

    def poses(self, from_ms: int, to_ms: int, robot_id: str | None = None,
              limit: int = 100_000) -> list[PoseRow]:
        # PREWHERE on sorting-key columns only: duplicates of one identity pass or fail
        # together, so FINAL still sees all of them; the other columns are read only for
        # granules holding rows of the window.
        where = "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        params: dict = {"f": from_ms, "t": to_ms, "n": limit}
        if robot_id is not None:
            where += " AND robot_id = {r:String}"
            params["r"] = robot_id
        return self._pose_query(
            f"SELECT {_POSE_COLUMNS} FROM {self.database}.poses FINAL PREWHERE {where} "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            params,
        )

    def poses_downsampled(self, from_ms: int, to_ms: int, step_ms: int,
                          robot_id: str | None = None, limit: int = 100_000) -> list[PoseRow]:
        """Per robot and step bucket [from + k*step, from + (k+1)*step), its first pose in
        from_ms <= event time < to_ms; ordered by time then robot, like poses()."""
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        where = "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
        params: dict = {"f": from_ms, "t": to_ms, "s": step_ms, "n": limit}
        if robot_id is not None:
            where += " AND robot_id = {r:String}"
            params["r"] = robot_id
        aligned = from_ms % KEYFRAME_MS == 0 and step_ms % KEYFRAME_MS == 0
        if aligned or step_ms >= 10 * KEYFRAME_MS:
            return self._pose_query(self._keyframe_sql(aligned, robot_id), params)
        return self._pose_query(
            f"SELECT {_POSE_COLUMNS} FROM (SELECT * FROM {self.database}.poses FINAL WHERE {where} "
            "ORDER BY robot_id, ts "
            "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
            f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            params,
        )

    def _keyframe_sql(self, aligned: bool, robot_id: str | None) -> str:
        """poses_downsampled from the per-minute keyframes (schema v4), exactly.

        A step [b, b + step) is a head [b, next whole minute), then minutes starting in it.
        Its first pose is either in the head, or the first pose of the first of those
        minutes holding one in the step, i.e. that minute's keyframe (a minute cut by the
        step's end counts only if its keyframe is before the end). So the candidates are
        the keyframes in the window plus every pose in the heads, read from `poses`: none
        when `from` and the step are whole minutes, a minute per step at most otherwise
        (steps of 10 min or more, so at most a tenth of the window; only the time column
        of the rest is read, to find them).
        """
        db = self.database
        robot = " AND robot_id = {r:String}" if robot_id is not None else ""
        window = ("ts >= fromUnixTimestamp64Milli({f:Int64}) "
                  "AND ts < fromUnixTimestamp64Milli({t:Int64})")
        candidates = (
            f"SELECT {POSE_COLUMNS} FROM {db}.pose_keyframes FINAL "
            "PREWHERE cell >= toStartOfMinute(fromUnixTimestamp64Milli({f:Int64})) "
            f"AND cell < fromUnixTimestamp64Milli({{t:Int64}}){robot} WHERE {window}")
        if not aligned:
            # The head of the step a pose falls in ends at the minute after the step's start.
            start = ("({f:Int64} + intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64}) "
                     "* {s:Int64})")
            candidates += (
                f" UNION ALL SELECT {POSE_COLUMNS} FROM {db}.poses FINAL PREWHERE {window}{robot} "
                f"AND toUnixTimestamp64Milli(ts) < intDiv({start} + {KEYFRAME_MS - 1}, "
                f"{KEYFRAME_MS}) * {KEYFRAME_MS}")
        return (f"SELECT {_POSE_COLUMNS} FROM (SELECT * FROM ({candidates}) ORDER BY robot_id, ts "
                "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
                f"ORDER BY ts, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}")

    def map_at(self, at_ms: int) -> list[ChunkState]:
        """Every chunk's winning write at or before `at_ms` (nearest snapshot + events).

        One statement: the nearest snapshot's time is a scalar subquery (ClickHouse folds
        it to a constant before choosing granules). Without a snapshot it is the epoch, so
        the snapshot side is empty and every event <= `at_ms` is folded.
        """
        db = self.database
        with self._reader() as c:
            rows = c.query(
                f"WITH (SELECT max(snap_ts) FROM {db}.snapshot_log "
                "WHERE snap_ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"AND snap_ts < {self._valid_before()}) AS snap "
                "SELECT row, col, toUnixTimestamp64Milli(max(ts)), argMax(robot_id, (ts, robot_id)), "
                "lower(hex(argMax(content_hash, (ts, robot_id)))) "
                f"FROM (SELECT row, col, ts, robot_id, content_hash FROM {db}.map_snapshots "
                "WHERE snap_ts = snap UNION ALL "
                f"SELECT row, col, ts, robot_id, content_hash FROM {db}.chunk_events "
                "WHERE ts > snap AND ts <= fromUnixTimestamp64Milli({t:Int64})) "
                "GROUP BY row, col ORDER BY row, col", parameters={"t": at_ms}).result_rows
        return [ChunkState(*r) for r in rows]

    def robots_at(self, at_ms: int) -> list[PoseRow]:
        """Each robot's latest pose at or before `at_ms` (nearest snapshot + events).

        A robot that reported in (snapshot, at_ms] is answered by one pass over those poses
        (its latest there is its latest <= at_ms); only robots silent since the snapshot
        need the snapshot's time of their last pose and a lookup of that row.
        """
        db = self.database
        with self._reader() as c:
            # The nearest snapshot and its robots (max(ts): a rebuilt snapshot may still
            # hold its older rows until merged).
            listed = c.query(
                f"WITH (SELECT max(snap_ts) FROM {db}.snapshot_log "
                "WHERE snap_ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"AND snap_ts < {self._valid_before()}) AS snap "
                "SELECT toUnixTimestamp64Milli(any(snap)), robot_id "
                f"FROM {db}.robot_snapshots WHERE snap_ts = snap GROUP BY robot_id",
                parameters={"t": at_ms}).result_rows
            snap = listed[0][0] if listed else self._snapshot_at_or_before(at_ms, c)
            if snap is None:
                columns = c.query(
                    f"SELECT {_POSE_COLUMNS} FROM {db}.poses FINAL WHERE (robot_id, ts) IN ("
                    f"SELECT robot_id, max(ts) FROM {db}.poses "
                    "WHERE ts <= fromUnixTimestamp64Milli({t:Int64}) GROUP BY robot_id) "
                    f"ORDER BY robot_id {_FINAL_SETTINGS}", parameters={"t": at_ms}).result_columns
                return _pose_rows(columns)
            params: dict = {"t": at_ms, "p": snap}
            recent = _pose_rows(c.query(
                f"SELECT {_POSE_COLUMNS} FROM {db}.poses FINAL "
                "PREWHERE ts > fromUnixTimestamp64Milli({p:Int64}) "
                "AND ts <= fromUnixTimestamp64Milli({t:Int64}) "
                f"ORDER BY robot_id, ts DESC LIMIT 1 BY robot_id {_FINAL_SETTINGS}",
                parameters=params).result_columns)
            seen = {r.robot_id for r in recent}
            params["silent"] = [robot for _, robot in listed if robot not in seen]
            if not params["silent"]:
                return recent  # ordered by robot id
            silent = _pose_rows(c.query(
                f"SELECT {_POSE_COLUMNS} FROM {db}.poses FINAL WHERE (robot_id, ts) IN ("
                f"SELECT robot_id, max(ts) FROM {db}.robot_snapshots "
                "WHERE snap_ts = fromUnixTimestamp64Milli({p:Int64}) "
                "AND has({silent:Array(String)}, robot_id) GROUP BY robot_id) "
                f"{_FINAL_SETTINGS}", parameters=params).result_columns)
        return sorted(recent + silent, key=lambda r: r.robot_id)

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        # PREWHERE on the sorting key's `ts`: as in poses(), FINAL sees every duplicate.
        rows = self._rows(
            f"SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_id LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def timeline(self, from_ms: int, to_ms: int, buckets: int) -> list[TimelineBucket]:
        bucket_ms, starts = timeline_buckets(from_ms, to_ms, buckets)
        if not starts:
            return []
        db = self.database
        params = {"f": from_ms, "t": to_ms, "b": bucket_ms}
        window = ("ts >= fromUnixTimestamp64Milli({f:Int64}) "
                  "AND ts < fromUnixTimestamp64Milli({t:Int64})")
        bucket = "intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {b:Int64})"
        chunks = dict(self._rows(
            f"SELECT {bucket} AS k, count() FROM {db}.chunk_events FINAL PREWHERE {window} "
            f"GROUP BY k {_FINAL_SETTINGS}", params))
        if from_ms % KEYFRAME_MS == 0 and bucket_ms % KEYFRAME_MS == 0:
            # Buckets of whole minutes: a robot has a pose in a bucket iff it has a
            # keyframe (its first pose of a minute) there.
            robots = dict(self._rows(
                f"SELECT {bucket} AS k, uniqExact(robot_id) FROM {db}.pose_keyframes FINAL "
                "PREWHERE cell >= fromUnixTimestamp64Milli({f:Int64}) "
                "AND cell < fromUnixTimestamp64Milli({t:Int64}) "
                f"WHERE ts < fromUnixTimestamp64Milli({{t:Int64}}) GROUP BY k {_FINAL_SETTINGS}",
                params))
        else:  # a duplicate pose names the same robot: no FINAL needed
            robots = dict(self._rows(
                f"SELECT {bucket} AS k, uniqExact(robot_id) FROM {db}.poses PREWHERE {window} "
                "GROUP BY k", params))
        conflicts = self.conflict_counts(from_ms, to_ms, bucket_ms)
        return [TimelineBucket(start, chunks.get(k, 0), conflicts.get(start, 0), robots.get(k, 0))
                for k, start in enumerate(starts)]

    def robot_known(self, robot_id: str) -> bool:
        # pose_keyframes is sorted by robot: a primary-key lookup, not a scan of `poses`.
        return bool(self._rows(
            f"SELECT 1 FROM {self.database}.pose_keyframes WHERE robot_id = {{r:String}} LIMIT 1",
            {"r": robot_id}))

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        rows = self._rows(
            f"SELECT width, height, zlib_pixels FROM {self.database}.chunk_contents "
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
        rows = self._rows(
            f"SELECT content_hash, any(width), any(height), any(zlib_pixels) "
            f"FROM {self.database}.chunk_contents WHERE content_hash IN "
            "(SELECT arrayJoin(arrayMap(h -> toFixedString(unhex(h), 16), {hs:Array(String)}))) "
            "GROUP BY content_hash",
            {"hs": [h.hex() for h in set(hashes)]},
            column_formats={"content_hash": "bytes", "any(zlib_pixels)": "bytes"},
        )
        return {bytes(h): (w, ht, bytes(d)) for h, w, ht, d in rows}

    def latest_meta(self) -> MapMetaSet | None:
        rows = self._rows(
            f"SELECT meta FROM {self.database}.map_meta FINAL ORDER BY ts DESC LIMIT 1", {})
        if not rows:
            return None
        doc = msgspec.json.decode(rows[0][0])
        return MapMetaSet.from_2019(doc)

    # --- conflicts ------------------------------------------------------------------

    def chunk_writes_near(self, chunks: Sequence[tuple[int, int]], from_ms: int,
                          to_ms: int) -> list[ChunkRow]:
        if not chunks:
            return []
        rows = self._rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)), "
            f"recv_lag_ms FROM {self.database}.chunk_events FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts <= fromUnixTimestamp64Milli({t:Int64}) "
            "WHERE (row, col) IN (SELECT tupleElement(c, 1), tupleElement(c, 2) "
            "FROM (SELECT arrayJoin({cs:Array(Tuple(UInt16, UInt16))}) AS c)) "
            f"ORDER BY ts, row, col, robot_id {_FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "cs": [tuple(c) for c in set(chunks)]},
        )
        return [ChunkRow(r[0], r[1], r[2], r[3], r[4], r[2] + r[5]) for r in rows]

    def conflicts(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ConflictRow]:
        rows = self._rows(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_a, toUnixTimestamp64Milli(ts_a), "
            f"robot_b FROM {self.database}.conflicts FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"ORDER BY ts, row, col, robot_b LIMIT {{n:UInt32}} {_FINAL_SETTINGS}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ConflictRow(*r) for r in rows]

    def conflict_counts(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        if bucket_ms <= 0:
            raise ValueError("bucket_ms must be positive")
        # Without FINAL: count distinct identities, the same number FINAL would give.
        rows = self._rows(
            "SELECT {f:Int64} + intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {b:Int64}) * {b:Int64} "
            "AS start, uniqExact(ts, row, col, robot_b) "
            f"FROM {self.database}.conflicts "
            "WHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "GROUP BY start ORDER BY start",
            {"f": from_ms, "t": to_ms, "b": bucket_ms},
        )
        return {int(start): int(n) for start, n in rows}
