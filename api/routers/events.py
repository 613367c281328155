"""Replay windows: every chunk change in [from, to) and the poses, downsampled on request.

A replay at speed S showing F frames a second asks for `step_ms` = S / F seconds of
history (86400x at 10 frames/s: 8,640,000). Whole-minute `from` and `step_ms`, or any
`from` with a step of 10 min or more, are answered from per-minute keyframes (schema v4:
a day costs about as much as its frames); smaller odd steps from every pose. Both exact.

Chunk changes are never dropped by `step_ms`. At thousands of times real time they are too
many to fetch (86400x: ~3.4 M a second of playback at 200 robots), so `chunk_step_ms` > 0
keeps per chunk and absolute bucket [k*step, (k+1)*step) only the bucket's winner, computed
at query time; the map folded from them is exact at every bucket boundary.
"""

from __future__ import annotations

import msgspec
from fastapi import APIRouter, Depends, Query, Response
from pydantic import BaseModel

from mapservice.core.wire2019 import format_timestamps

from ..access import READ
from ..deps import ClockDep, HistoryDep, SettingsDep, WindowQuery, check_step
from .chunk_events import ChunkEvent
from .poses import Pose

router = APIRouter(prefix="/api/v1/events", tags=["events"], dependencies=[Depends(READ)])
MAX_SPAN_MS = 86_400_000
MAX_CHUNKS = 1_000_000
MAX_POSES = 200_000
_encode = msgspec.json.Encoder().encode


class Events(BaseModel):
    from_ms: int
    to_ms: int
    step_ms: int
    chunk_step_ms: int = 0
    chunks: list[ChunkEvent]
    poses: list[Pose]
    truncated: bool


def chunk_doc(r, timestamp: str) -> dict:
    return {
        "row": r.row,
        "column": r.column,
        "timestamp": timestamp,
        "ts_ms": r.ts_ms,
        "receive_time_ms": r.receive_time_ms,
        "robotId": r.robot_id,
        "content_hash": r.content_hash,
    }


def pose_doc(r, timestamp: str) -> dict:
    return {
        "robotId": r.robot_id,
        "timestamp": timestamp,
        "ts_ms": r.ts_ms,
        "receive_time_ms": r.receive_time_ms,
        "position": (r.x, r.y, r.z),
        "orientation": (r.qx, r.qy, r.qz, r.qw),
        "battery_level": r.battery_level,
        "charging": r.charging,
        "loaded": r.loaded,
        "path": r.path,
    }


@router.get(
    "",
    operation_id="listEvents",
    response_model=Events,
    description=(
        "Chunk changes in [from, to) in event-time order, all of them, and poses: every pose, "
        "or with step_ms > 0 each robot's first pose in every step [from + k*step_ms, ...); "
        "with chunk_step_ms > 0 only each chunk's last change per bucket (fast replays). "
        "`truncated` is true when the window held more than "
        f"{MAX_CHUNKS:,} chunk changes or {MAX_POSES:,} poses: the answer then covers "
        "[from, to_ms) completely; ask again from to_ms. At most 24 h per request."
    ),
)
def list_events(
    window: WindowQuery,
    step_ms: int = Query(
        0,
        description="0: every pose; > 0: at most one pose per robot per "
        "step (whole minutes from a whole-minute 'from', or "
        ">= 600000 from any 'from', are fastest)",
    ),
    chunk_step_ms: int = Query(
        0,
        description="0: every chunk change; > 0: per chunk and "
        "absolute bucket [k*chunk_step_ms, "
        "(k+1)*chunk_step_ms) only its winning change "
        "(the map stays exact at every bucket boundary)",
    ),
    *,
    store: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> Response:
    check_step(step_ms)
    check_step(chunk_step_ms, "chunk_step_ms", "every chunk change")
    f, t = window.in_retention(MAX_SPAN_MS, settings, clock.now_ms())
    chunks = (
        store.chunk_events_compacted(f, t, chunk_step_ms, MAX_CHUNKS + 1)
        if chunk_step_ms > 0
        else store.chunk_events(f, t, MAX_CHUNKS + 1)
    )
    poses = (
        store.poses_downsampled(f, t, step_ms, limit=MAX_POSES + 1)
        if step_ms > 0
        else store.poses(f, t, limit=MAX_POSES + 1)
    )
    truncated = len(chunks) > MAX_CHUNKS or len(poses) > MAX_POSES
    if truncated:
        # Cut both before the first instant a list may hold only part of, so that
        # [from, cut) is complete and the next request (from = cut) repeats nothing.
        cut = min(
            rows[-1].ts_ms
            for rows, cap in ((chunks, MAX_CHUNKS), (poses, MAX_POSES))
            if len(rows) > cap
        )
        chunks = [r for r in chunks if r.ts_ms < cut]
        poses = [r for r in poses if r.ts_ms < cut]
        t = cut
    body = {
        "from_ms": f,
        "to_ms": t,
        "step_ms": step_ms,
        "chunk_step_ms": chunk_step_ms,
        "truncated": truncated,
        "chunks": [chunk_doc(r, ts) for r, ts in zip(chunks, _timestamps(chunks))],
        "poses": [pose_doc(r, ts) for r, ts in zip(poses, _timestamps(poses))],
    }
    # Encoded directly: a day of a fleet is hundreds of thousands of objects, too many to
    # validate one by one (the response model documents the same shape).
    return Response(_encode(body), media_type="application/json")


def _timestamps(rows) -> list[str]:
    return format_timestamps([r.ts_ms for r in rows])
