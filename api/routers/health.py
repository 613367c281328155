"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor

from fastapi import APIRouter, Depends, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from mapservice.runtime.health import failing_reasons

from ..access import METRICS, PUBLIC
from ..deps import AdvisoryDep, LivenessDep, ReadinessDep

router = APIRouter(tags=["health"])


# The probes are open: the kubelet sends no credential, and they tell nothing but up or down.
# They are async and never take a thread of the reads' pool: the reads' threads may all be
# busy, and a probe must still answer within a second. The checks read cached state
# (mapservice/runtime/health.py CachedCheck) and never run a query themselves.
PROBES = ThreadPoolExecutor(max_workers=1, thread_name_prefix="probes")


async def _evaluate(checks: Mapping[str, Callable[[], bool]]) -> dict[str, bool]:
    """Each check's answer: on the event loop when every check can answer without waiting
    (a CachedCheck with an answer, a heartbeat), else in the probes' thread (a
    CachedCheck's very first call waits for the dependency)."""
    answers = {name: _nowait(check) for name, check in checks.items()}
    if all(answer is not None for answer in answers.values()):
        return answers  # type: ignore[return-value]

    def run() -> dict[str, bool]:
        return {name: bool(check()) for name, check in checks.items()}

    return await asyncio.get_running_loop().run_in_executor(PROBES, run)


def _nowait(check: Callable[[], object]) -> bool | None:
    nowait = getattr(check, "nowait", None)
    if nowait is not None:
        answer = nowait()
        return None if answer is None else bool(answer)
    return bool(check())  # the process's own state (heartbeats, flags): never waits


@router.get("/healthz", operation_id="getLiveness", dependencies=[Depends(PUBLIC)])
async def liveness(heartbeats: LivenessDep) -> JSONResponse:
    """Alive: this answer needs the event loop; with the processors in this process, also
    their loops' heartbeats (mapservice/runtime/health.py)."""
    checks = await _evaluate(heartbeats)
    ok = all(checks.values())
    body = {"ok": ok, "checks": checks} if checks else {"ok": True}
    return JSONResponse(body, status_code=200 if ok else 503)


@router.get("/readyz", operation_id="getReadiness", dependencies=[Depends(PUBLIC)])
async def readiness(required: ReadinessDep, advisory: AdvisoryDep) -> JSONResponse:
    """Ready: a real call to each required dependency; advisory ones (Kafka for the API
    alone) are reported in `checks` but do not make it unready."""
    checks = await _evaluate(required)
    ok = all(checks.values())
    # Why a failed check failed, where it can say (the history store's inserts: since when,
    # the error); a reason is the check's in-memory state, so it never waits either.
    reasons = failing_reasons(required, checks)
    checks.update(await _evaluate(advisory))
    return JSONResponse(
        {"ok": ok, "checks": checks, **({"reasons": reasons} if reasons else {})},
        status_code=200 if ok else 503,
    )


@router.get(
    "/metrics", operation_id="getMetrics", include_in_schema=False, dependencies=[Depends(METRICS)]
)
def metrics() -> Response:
    return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
