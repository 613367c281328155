"""Who the caller is to this service: the role of the token a request carries and the
scopes it opens. The replay page asks before it offers editing: only a token with the
`operator` scope shapes the floor, and the page shows edit controls to no one else."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from pydantic import BaseModel

from ..access import READ
from ..credentials import GRANTS, Caller

router = APIRouter(prefix="/api/v1/caller", tags=["access"])

CallerDep = Annotated[Caller, Depends(READ)]


class CallerAccess(BaseModel):
    role: str | None  # None: no token, or (while reads are open) one that is none of ours
    scopes: list[str]  # what the token opens: read, write, operator, admin, metrics


@router.get("", operation_id="getCallerAccess", response_model=CallerAccess)
def get_caller_access(caller: CallerDep) -> CallerAccess:
    """The role and scopes of the bearer token sent (nothing of the token itself)."""
    scopes = sorted(s.value for s in GRANTS[caller.role]) if caller.role else []
    return CallerAccess(role=caller.role, scopes=scopes)
