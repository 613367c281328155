"""One robot's track aggregated per time bucket, as pure functions: the rule every store's
`track_buckets` follows (the memory store folds with it; tests check ClickHouse against it).

The window [from, to) of one robot's poses (one per event time, as the store keeps them)
is cut at absolute multiples of the bucket size, [k*bucket_ms, (k+1)*bucket_ms): the same
instants are bucket edges in every window read with that size, and a bucket holds a
pose only if it meets the window.

- **Distance.** A step joins two consecutive poses of the robot in the window, by event
  time; its length is the straight line between their (x, y) positions, in metres as
  stored (to the millimetre). It counts once, in the bucket of its later pose. The
  window's first pose starts no step (a step from a pose before the window belongs to the
  window before), so the buckets' distances add up to the window's total, whatever their
  size: every bucketing of a window counts its steps once. The step over a silent gap
  counts where the robot reappears.
- **Speed.** A bucket's distance over the time its steps span (`step_ms`: from the pose
  before its first pose to its last pose), the mean speed while the robot's poses cover
  the bucket. Distance and time add up the same way, so a longer stretch's mean speed is
  the sum of its buckets' distances over the sum of their `step_ms`.
- **Battery.** The lowest, highest and mean level of the bucket's poses that report one
  (None where none does).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from mapservice.core.ports import PoseRow, TrackBucket

SECOND_MS = 1000
MINUTE_MS = 60 * SECOND_MS
HOUR_MS = 60 * MINUTE_MS
DAY_MS = 24 * HOUR_MS
# Round sizes, each dividing the next larger unit (a minute, an hour, a day): a bucket edge
# is a round UTC instant and a day is whole buckets at every size up to a day.
BUCKET_SIZES_MS = (
    SECOND_MS,
    2 * SECOND_MS,
    5 * SECOND_MS,
    10 * SECOND_MS,
    15 * SECOND_MS,
    30 * SECOND_MS,
    MINUTE_MS,
    2 * MINUTE_MS,
    5 * MINUTE_MS,
    10 * MINUTE_MS,
    15 * MINUTE_MS,
    30 * MINUTE_MS,
    HOUR_MS,
    2 * HOUR_MS,
    3 * HOUR_MS,
    6 * HOUR_MS,
    12 * HOUR_MS,
    DAY_MS,
)


def buckets_in(from_ms: int, to_ms: int, bucket_ms: int) -> int:
    """How many absolute buckets of `bucket_ms` meet [from_ms, to_ms) (0 when it is empty)."""
    if bucket_ms <= 0:
        raise ValueError("bucket_ms must be positive")
    if to_ms <= from_ms:
        return 0
    return (to_ms - 1) // bucket_ms - from_ms // bucket_ms + 1


def bucket_size_for(from_ms: int, to_ms: int, max_buckets: int) -> int:
    """The smallest round bucket size (BUCKET_SIZES_MS, then whole days) with at most
    `max_buckets` buckets meeting [from_ms, to_ms): the size follows from the span alone."""
    if max_buckets < 2:
        # A window off the bucket edges meets two buckets of any size it fits in.
        raise ValueError("max_buckets must be at least 2")
    for size in BUCKET_SIZES_MS:
        if buckets_in(from_ms, to_ms, size) <= max_buckets:
            return size
    # Fewer days than span / max_buckets make more buckets than that: start there.
    days = max(1, math.ceil((to_ms - from_ms) / max_buckets / DAY_MS))
    while buckets_in(from_ms, to_ms, days * DAY_MS) > max_buckets:
        days += 1
    return days * DAY_MS


def step_length_m(a: PoseRow, b: PoseRow) -> float:
    """The straight line from `a` to `b` in the plane (x, y), metres."""
    return math.hypot(b.x - a.x, b.y - a.y)


def fold_track_buckets(
    poses: Iterable[PoseRow], from_ms: int, to_ms: int, bucket_ms: int
) -> list[TrackBucket]:
    """The buckets of one robot's `poses` (any order; one per event time) in [from_ms,
    to_ms), those holding a pose, in time order (the module's rule)."""
    if bucket_ms <= 0:
        raise ValueError("bucket_ms must be positive")
    track = sorted((p for p in poses if from_ms <= p.ts_ms < to_ms), key=lambda p: p.ts_ms)
    out: list[TrackBucket] = []
    previous: PoseRow | None = None
    group: list[PoseRow] = []
    steps, distance, step_ms = 0, 0.0, 0

    def close() -> None:
        levels = [p.battery_level for p in group if p.battery_level is not None]
        out.append(
            TrackBucket(
                start_ms=group[0].ts_ms // bucket_ms * bucket_ms,
                poses=len(group),
                steps=steps,
                distance_m=distance,
                step_ms=step_ms,
                first_ms=group[0].ts_ms,
                last_ms=group[-1].ts_ms,
                battery_min=min(levels) if levels else None,
                battery_max=max(levels) if levels else None,
                battery_mean=sum(levels) / len(levels) if levels else None,
            )
        )

    for pose in track:
        if group and pose.ts_ms // bucket_ms != group[0].ts_ms // bucket_ms:
            close()
            group, steps, distance, step_ms = [], 0, 0.0, 0
        group.append(pose)
        if previous is not None:
            steps += 1
            distance += step_length_m(previous, pose)
            step_ms += pose.ts_ms - previous.ts_ms
        previous = pose
    if group:
        close()
    return out


def mean_speed_mps(bucket: TrackBucket) -> float | None:
    """The bucket's distance over the time its steps span; None without a step of time."""
    return bucket.distance_m / (bucket.step_ms / 1000) if bucket.step_ms > 0 else None
