"""Conflicts: two robots writing different content to one chunk within the conflict window
(rule in mapservice/core/conflicts.py), in a time window, ordered by time. The store keeps who
and when; both writes' content hashes come from the chunk history, so one call gives the
replay's conflict inspector both writes (robot, time, pixels at
/api/v1/chunk-contents/{hash}) and where to seek to see the later one on the map.

A map upload is never a conflict: the processors do not record one for the map uploader's
writes, and rows naming it that an older processor recorded are left out here too."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.core.change_feed import UPLOADER_ID
from mapservice.core.ports import ConflictReader, ConflictRow

from ..access import READ
from ..deps import ConflictsDep, SettingsDep, WindowQuery

router = APIRouter(prefix="/api/v1/conflicts", tags=["conflicts"], dependencies=[Depends(READ)])


class Conflict(BaseModel):
    row: int
    column: int
    ts_ms: int  # event time of the later write (robot_b's)
    robot_a: str  # of the latest earlier write that conflicts with robot_b's
    ts_a_ms: int
    hash_a: str | None  # None only if the write left the history (DELETE) meanwhile
    robot_b: str
    hash_b: str | None
    seek_ms: int  # just after the later write: the map there shows robot_b's content


class Conflicts(BaseModel):
    from_ms: int
    to_ms: int
    window_s: float
    rule: str  # the rule in words, for the inspector's readers
    conflicts: list[Conflict]
    truncated: bool


def rule_text(window_s: float) -> str:
    return (
        f"two robots wrote different pixels to one chunk at most {window_s:g} s apart; "
        f"the map upload ('{UPLOADER_ID}') is never part of a conflict"
    )


@router.get("", operation_id="listConflicts", response_model=Conflicts)
def list_conflicts(
    window: WindowQuery,
    limit: int = Query(10_000, ge=1, le=100_000),
    *,
    store: ConflictsDep,
    settings: SettingsDep,
) -> Conflicts:
    f, t = window.parse(settings.retention_ms)
    stored = store.conflicts(f, t, limit + 1)
    rows = [r for r in stored if UPLOADER_ID not in (r.robot_a, r.robot_b)]
    hashes = _content_hashes(store, rows[:limit])
    return Conflicts(
        from_ms=f,
        to_ms=t,
        window_s=settings.conflict_window_s,
        rule=rule_text(settings.conflict_window_s),
        truncated=len(stored) > limit,
        conflicts=[
            Conflict(
                row=r.row,
                column=r.column,
                ts_ms=r.ts_ms,
                robot_a=r.robot_a,
                ts_a_ms=r.ts_a_ms,
                robot_b=r.robot_b,
                hash_a=hashes.get((r.row, r.column, r.ts_a_ms, r.robot_a)),
                hash_b=hashes.get((r.row, r.column, r.ts_ms, r.robot_b)),
                seek_ms=r.ts_ms + 1,
            )
            for r in rows[:limit]
        ],
    )


def _content_hashes(
    store: ConflictReader, rows: list[ConflictRow]
) -> dict[tuple[int, int, int, str], str]:
    """(row, column, ts, robot) -> content hash of both writes of every conflict: one read
    of the conflicts' chunks over the span from the earliest A to the latest B."""
    if not rows:
        return {}
    writes = store.chunk_writes_near(
        sorted({(r.row, r.column) for r in rows}),
        min(r.ts_a_ms for r in rows),
        max(r.ts_ms for r in rows),
    )
    return {(w.row, w.column, w.ts_ms, w.robot_id): w.content_hash for w in writes}
