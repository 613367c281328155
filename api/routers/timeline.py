"""Timeline density: chunk changes, conflicts and active robots in N buckets of [from, to)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Query
from pydantic import BaseModel

from mapservice.core.timetravel import timeline_buckets

from ..access import READ
from ..deps import ClockDep, HistoryDep, SettingsDep, WindowQuery

router = APIRouter(prefix="/api/v1/timeline", tags=["timeline"], dependencies=[Depends(READ)])
MAX_BUCKETS = 2000


class Bucket(BaseModel):
    start_ms: int
    chunk_changes: int
    conflicts: int
    robots_active: int


class Timeline(BaseModel):
    from_ms: int
    to_ms: int
    bucket_ms: int
    buckets: list[Bucket]


@router.get(
    "",
    operation_id="getTimeline",
    response_model=Timeline,
    description=(
        "[from, to) cut into at most `buckets` equal buckets of bucket_ms (whole ms; the last "
        "one may end after `to`, nothing after `to` counts). Per bucket: chunk changes, "
        "conflicts (by the later write's time) and robots with at least one pose."
    ),
)
def get_timeline(
    window: WindowQuery,
    buckets: int = Query(200, description=f"Number of buckets, 1 to {MAX_BUCKETS}"),
    *,
    store: HistoryDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> Timeline:
    if not 1 <= buckets <= MAX_BUCKETS:
        raise HTTPException(
            400,
            f"buckets ({buckets}) must be between 1 and {MAX_BUCKETS}; "
            "a timeline needs no more buckets than it has pixels",
        )
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    bucket_ms, _ = timeline_buckets(f, t, buckets)
    return Timeline(
        from_ms=f,
        to_ms=t,
        bucket_ms=bucket_ms,
        buckets=[
            Bucket(
                start_ms=b.start_ms,
                chunk_changes=b.chunk_changes,
                conflicts=b.conflicts,
                robots_active=b.robots_active,
            )
            for b in store.timeline(f, t, buckets)
        ],
    )
