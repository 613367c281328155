"""What the history holds: row counts per table (duplicates already folded)."""

from __future__ import annotations

import msgspec
from fastapi import APIRouter, Depends

from mapservice.core.ports import StoreAdmin

from ..access import READ
from ..deps import get_store

router = APIRouter(prefix="/api/v1/stats", tags=["stats"], dependencies=[Depends(READ)])


@router.get("", operation_id="getHistoryStats")
def get_stats(store: StoreAdmin = Depends(get_store)) -> dict:
    return msgspec.structs.asdict(store.counts())
