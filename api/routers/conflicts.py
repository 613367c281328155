"""Conflicts: two robots writing different content to one chunk within the conflict window
(rule in mapservice/conflicts.py), in a time window, ordered by time."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query
from pydantic import BaseModel

from mapservice.ports import HistoryStore
from mapservice.settings import Settings

from ..deps import get_settings, get_store, parse_window

router = APIRouter(prefix="/api/v1/conflicts", tags=["conflicts"])


class Conflict(BaseModel):
    row: int
    column: int
    ts_ms: int  # event time of the later write (robot_b's)
    robot_a: str
    ts_a_ms: int
    hash_a: str
    robot_b: str
    hash_b: str


class Conflicts(BaseModel):
    from_ms: int
    to_ms: int
    window_s: float
    conflicts: list[Conflict]
    truncated: bool


@router.get("", operation_id="listConflicts", response_model=Conflicts)
def list_conflicts(
    from_: str = Query(..., alias="from", description="Start (inclusive), ISO 8601 or epoch ms"),
    to: str = Query(..., description="End (exclusive), ISO 8601 or epoch ms"),
    limit: int = Query(10_000, ge=1, le=100_000),
    store: HistoryStore = Depends(get_store),
    settings: Settings = Depends(get_settings),
) -> Conflicts:
    f, t = parse_window(from_, to, settings.retention_ms)
    rows = store.conflicts(f, t, limit + 1)
    return Conflicts(from_ms=f, to_ms=t, window_s=settings.conflict_window_s, truncated=len(rows) > limit,
                     conflicts=[Conflict(**{k: getattr(r, k) for k in Conflict.model_fields})
                                for r in rows[:limit]])
