"""The rows of the timeline and the plots that TimeTravelReader (ports.py, which names them)
answers with: activity per bucket of the floor, and one robot's per bucket of a window."""

from __future__ import annotations

import msgspec


class TimelineBucket(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """Activity in [start_ms, start_ms + bucket_ms): chunk writes, conflicts (by their
    `ts`) and robots with at least one pose."""

    start_ms: int
    chunk_changes: int
    conflicts: int
    robots_active: int


class TrackBucket(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """One robot over one bucket [start_ms, start_ms + bucket_ms) of a window, from every
    pose it stored there (core/track_buckets.py has the rule): its poses, the steps that end
    in the bucket (from the robot's previous pose in the window), their length in metres
    (x, y) and the time they span, and the battery's range and mean over its poses."""

    start_ms: int
    poses: int
    steps: int
    distance_m: float
    step_ms: int  # the time the steps span: distance_m / step_ms is the mean speed
    first_ms: int
    last_ms: int
    battery_min: float | None
    battery_max: float | None
    battery_mean: float | None
