"""The time-travel benchmark's naive queries: each answer `bench timetravel` times, computed
the slow way (the latest write per chunk or pose over the whole history, every pose, every
event), to compare the store's answers and latencies against."""

from __future__ import annotations


def naive_map_at(store, at_ms: int) -> list:
    """Latest write per chunk over all history <= T: no snapshot, one GROUP BY."""
    from mapservice.core.ports import ChunkState

    db = store.database
    with store.lock:
        rows = store.client.query(
            "SELECT row, col, toUnixTimestamp64Milli(max(ts)), argMax(robot_id, (ts, robot_id)), "
            "lower(hex(argMax(content_hash, (ts, robot_id)))) "
            f"FROM {db}.chunk_events WHERE ts <= fromUnixTimestamp64Milli({{t:Int64}}) "
            "GROUP BY row, col ORDER BY row, col",
            parameters={"t": at_ms},
        ).result_rows
    return [ChunkState(*r) for r in rows]


def naive_robots_at(store, at_ms: int) -> list[tuple[str, int]]:
    """(robot, time of its latest pose <= T) over all poses: no snapshot."""
    db = store.database
    with store.lock:
        return [
            tuple(r)
            for r in store.client.query(
                f"SELECT robot_id, toUnixTimestamp64Milli(max(ts)) FROM {db}.poses "
                "WHERE ts <= fromUnixTimestamp64Milli({t:Int64}) GROUP BY robot_id ORDER BY robot_id",
                parameters={"t": at_ms},
            ).result_rows
        ]


def naive_poses_downsampled(store, from_ms: int, to_ms: int, step_ms: int) -> list:
    """poses_downsampled from every pose (the query before the keyframes of schema v4)."""
    from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS, POSE_READ_COLUMNS

    return store.pose_query(
        f"SELECT {POSE_READ_COLUMNS} FROM (SELECT * FROM {store.database}.poses FINAL "
        "WHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
        "ORDER BY robot_id, ts "
        "LIMIT 1 BY robot_id, intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {s:Int64})) "
        f"ORDER BY ts, robot_id LIMIT 100000 {FINAL_SETTINGS}",
        {"f": from_ms, "t": to_ms, "s": step_ms},
    )


def naive_timeline(store, from_ms: int, to_ms: int, buckets: int) -> list:
    """The timeline from every event (the query before schema v9): chunk changes counted
    with FINAL, robots from every pose, per bucket."""
    from mapservice.core.ports import TimelineBucket
    from mapservice.core.timetravel import timeline_buckets

    bucket_ms, starts = timeline_buckets(from_ms, to_ms, buckets)
    db = store.database
    params = {"f": from_ms, "t": to_ms, "b": bucket_ms}
    window = (
        "ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64})"
    )
    bucket = "intDiv(toUnixTimestamp64Milli(ts) - {f:Int64}, {b:Int64})"
    with store.lock:
        chunks = dict(
            store.client.query(
                f"SELECT {bucket} AS k, count() FROM {db}.chunk_events FINAL WHERE {window} GROUP BY k",
                parameters=params,
            ).result_rows
        )
        robots = dict(
            store.client.query(
                f"SELECT {bucket} AS k, uniqExact(robot_id) FROM {db}.poses WHERE {window} GROUP BY k",
                parameters=params,
            ).result_rows
        )
    conflicts = store.conflict_counts(from_ms, to_ms, bucket_ms)
    return [
        TimelineBucket(start, chunks.get(k, 0), conflicts.get(start, 0), robots.get(k, 0))
        for k, start in enumerate(starts)
    ]
