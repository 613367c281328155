"""What the history holds: row counts per table (duplicates already folded)."""

from __future__ import annotations

import msgspec
from fastapi import APIRouter, Depends

from ..access import READ
from ..deps import AdminDep

router = APIRouter(prefix="/api/v1/stats", tags=["stats"], dependencies=[Depends(READ)])


@router.get("", operation_id="getHistoryStats")
def get_stats(store: AdminDep) -> dict:
    return msgspec.structs.asdict(store.counts())
