"""What the service is doing now that a reader of its history should know: whether the
history is being stored (the replay UI shows "history not stored since HH:MM:SS").

Readiness says the same to an orchestrator (`history_store` in /readyz); this is the
reader's view of it, behind the read scope like the history itself.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends
from pydantic import BaseModel

from ..access import READ
from ..deps import HistoryStatusSource

router = APIRouter(prefix="/api/v1/status", tags=["status"], dependencies=[Depends(READ)])


class HistoryStatus(BaseModel):
    storing: bool  # false: inserts fail and are retried; nothing new is stored
    failing_since_ms: int | None  # the first failed insert of the current failure
    last_stored_ms: int | None  # the last successful insert (null: none since start)
    reason: str | None  # the error and what to do, while failing


class ServiceStatus(BaseModel):
    # null: this process does not store the history (the API running apart from the
    # processors); their /readyz and mapservice_history_insert_failing say it there.
    history: HistoryStatus | None


@router.get("", operation_id="getServiceStatus", response_model=ServiceStatus)
def get_status(source: HistoryStatusSource) -> ServiceStatus:
    return ServiceStatus(history=None if source is None else HistoryStatus(**source()))
