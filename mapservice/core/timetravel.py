"""Time travel, as pure functions: the state of the floor at an instant is a fold of events.

The rule every reconstruction follows (and tests check ClickHouse against): the map at T
holds, for each chunk, the write with the greatest (event time, robot id) among writes with
event time <= T; the robots at T are, per robot, the pose with the greatest event time <= T.
Receive order never matters, so late, out-of-order and duplicated events change nothing.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from mapservice.core.ports import ChunkRow, ChunkState, PoseRow


def chunk_order(row: ChunkRow | ChunkState) -> tuple[int, str]:
    return (row.ts_ms, row.robot_id)


def fold_map(
    events: Iterable[ChunkRow | ChunkState], at_ms: int
) -> dict[tuple[int, int], ChunkState]:
    """(row, column) -> the winning write at or before `at_ms`."""
    state: dict[tuple[int, int], ChunkState] = {}
    for e in events:
        if e.ts_ms > at_ms:
            continue
        key = (e.row, e.column)
        current = state.get(key)
        if current is None or chunk_order(e) > chunk_order(current):
            state[key] = ChunkState(e.row, e.column, e.ts_ms, e.robot_id, e.content_hash)
    return state


def fold_robots(poses: Iterable[PoseRow], at_ms: int) -> dict[str, PoseRow]:
    """robot id -> its latest pose at or before `at_ms`."""
    state: dict[str, PoseRow] = {}
    for p in poses:
        if p.ts_ms > at_ms:
            continue
        current = state.get(p.robot_id)
        if current is None or p.ts_ms > current.ts_ms:
            state[p.robot_id] = p
    return state


def timeline_buckets(from_ms: int, to_ms: int, buckets: int) -> tuple[int, list[int]]:
    """(bucket_ms, the buckets' starts) for [from_ms, to_ms) in at most `buckets` buckets
    of equal whole milliseconds (the last one may end past `to_ms`; nothing there counts)."""
    if buckets < 1:
        raise ValueError("buckets must be at least 1")
    span = max(0, to_ms - from_ms)
    bucket_ms = max(1, -(-span // buckets))
    return bucket_ms, list(range(from_ms, to_ms, bucket_ms))


def yaw(qx: float, qy: float, qz: float, qw: float) -> float:
    """Heading (rotation about z) of an orientation quaternion, radians in [-pi, pi]."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
