"""A robot's track over a window: where it was (x, y, heading) and its battery; and the
same window aggregated per bucket from every pose (distance, speed, battery range), the
plots' read."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Path, Query
from pydantic import BaseModel

from mapservice.core.ports import TimeTravelReader
from mapservice.core.timetravel import yaw
from mapservice.core.track_buckets import bucket_size_for, mean_speed_mps

from ..access import READ
from ..deps import ClockDep, HistoryDep, SettingsDep, WindowQuery, check_step

router = APIRouter(prefix="/api/v1/robots", tags=["robots"], dependencies=[Depends(READ)])
MAX_POINTS = 100_000
MAX_SPAN_EVERY_POSE_MS = 86_400_000
MAX_TRACK_BUCKETS = 1000


def check_known(store: TimeTravelReader, robot_id: str) -> None:
    """A 404 naming a robot that never reported (asked when a read found nothing)."""
    if not store.robot_known(robot_id):
        raise HTTPException(
            404,
            f"robot {robot_id!r} has no pose in the history; GET /api/v1/robots lists the robots",
        )


class TrackPoint(BaseModel):
    ts_ms: int
    x: float
    y: float
    yaw: float  # radians, counter-clockwise from +x, from the pose's quaternion
    battery_level: float | None


class Track(BaseModel):
    robotId: str
    from_ms: int
    to_ms: int
    points: list[TrackPoint]


@router.get(
    "/{robot_id}/track",
    operation_id="getRobotTrack",
    response_model=Track,
    description="The robot's poses in [from, to): every one (windows up to 24 h), or "
    f"with step_ms > 0 its first in every step (at most {MAX_POINTS:,} points, "
    "windows up to the retention). 404 if the robot never reported.",
)
def get_robot_track(
    robot_id: Annotated[str, Path(max_length=64)],
    window: WindowQuery,
    step_ms: int = Query(0, description="0: every pose; > 0: at most one point per step"),
    *,
    store: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> Track:
    check_step(step_ms)
    span = MAX_SPAN_EVERY_POSE_MS if step_ms == 0 else settings.retention_ms
    f, t = window.in_retention(span, settings, clock.now_ms())
    if step_ms and (t - f) // step_ms > MAX_POINTS:
        raise HTTPException(
            400,
            f"{(t - f) // step_ms:,} steps of {step_ms} ms is more than "
            f"{MAX_POINTS:,}; use step_ms >= {-(-(t - f) // MAX_POINTS)}",
        )
    rows = store.robot_track(robot_id, f, t, step_ms, limit=MAX_POINTS + 1)
    if not rows:
        check_known(store, robot_id)
    return Track(
        robotId=robot_id,
        from_ms=f,
        to_ms=t,
        points=[
            TrackPoint(
                ts_ms=r.ts_ms,
                x=r.x,
                y=r.y,
                yaw=yaw(r.qx, r.qy, r.qz, r.qw),
                battery_level=r.battery_level,
            )
            for r in rows[:MAX_POINTS]
        ],
    )


class TrackBucket(BaseModel):
    start_ms: int  # a multiple of bucket_ms; the bucket is [start_ms, start_ms + bucket_ms)
    poses: int
    steps: int  # steps ending in the bucket, each from the robot's previous pose in the window
    distance_m: float  # their length in the plane, metres
    step_ms: int  # the time they span
    speed_mps: float | None  # distance_m over step_ms (None without a step)
    first_ms: int  # the bucket's first and last pose
    last_ms: int
    battery_min: float | None  # over the bucket's poses that report a level
    battery_max: float | None
    battery_mean: float | None


class TrackBuckets(BaseModel):
    robotId: str
    from_ms: int
    to_ms: int
    bucket_ms: int
    distance_m: float  # the window's, the sum of its buckets'
    buckets: list[TrackBucket]


@router.get(
    "/{robot_id}/track-buckets",
    operation_id="getRobotTrackBuckets",
    response_model=TrackBuckets,
    description="The robot's poses in [from, to) (windows up to the retention) aggregated per "
    "bucket [k*bucket_ms, (k+1)*bucket_ms), from every pose: bucket_ms is the smallest round "
    "size (1 s, 2 s, 5 s ... 30 min, 1 h ... 1 d, then whole days) giving at most `buckets` "
    "buckets. A step joins two consecutive poses in the window and counts once, in the bucket "
    "of its later pose, so the buckets' distances add up to the window's at every size; "
    "speed is a bucket's distance over the time its steps span. Buckets without a pose are "
    "left out. 404 if the robot never reported.",
)
def get_robot_track_buckets(
    robot_id: Annotated[str, Path(max_length=64)],
    window: WindowQuery,
    buckets: int = Query(200, description=f"At most this many buckets, 2 to {MAX_TRACK_BUCKETS:,}"),
    *,
    store: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> TrackBuckets:
    if not 2 <= buckets <= MAX_TRACK_BUCKETS:
        raise HTTPException(
            400,
            f"buckets ({buckets}) must be between 2 and {MAX_TRACK_BUCKETS:,}; "
            "a plot needs no more buckets than it has pixels",
        )
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    bucket_ms = bucket_size_for(f, t, buckets)
    rows = store.track_buckets(robot_id, f, t, bucket_ms)
    if not rows:
        check_known(store, robot_id)
    return TrackBuckets(
        robotId=robot_id,
        from_ms=f,
        to_ms=t,
        bucket_ms=bucket_ms,
        distance_m=sum(b.distance_m for b in rows),
        buckets=[
            TrackBucket(
                start_ms=b.start_ms,
                poses=b.poses,
                steps=b.steps,
                distance_m=b.distance_m,
                step_ms=b.step_ms,
                speed_mps=mean_speed_mps(b),
                first_ms=b.first_ms,
                last_ms=b.last_ms,
                battery_min=b.battery_min,
                battery_max=b.battery_max,
                battery_mean=b.battery_mean,
            )
            for b in rows
        ],
    )
