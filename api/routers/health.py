"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from mapservice.runtime.health import failing_reasons

from ..access import METRICS, PUBLIC

router = APIRouter(tags=["health"])


# The probes are open: the kubelet sends no credential, and they tell nothing but up or down.
@router.get("/healthz", operation_id="getLiveness", dependencies=[Depends(PUBLIC)])
def liveness(request: Request) -> JSONResponse:
    """Alive: this answer needs the event loop; with the processors in this process, also
    their loops' heartbeats (mapservice/runtime/health.py)."""
    checks = {name: bool(check()) for name, check in getattr(request.app.state, "liveness", {}).items()}
    ok = all(checks.values())
    body = {"ok": ok, "checks": checks} if checks else {"ok": True}
    return JSONResponse(body, status_code=200 if ok else 503)


@router.get("/readyz", operation_id="getReadiness", dependencies=[Depends(PUBLIC)])
def readiness(request: Request) -> JSONResponse:
    """Ready: a real call to each required dependency; advisory ones (Kafka for the API
    alone) are reported in `checks` but do not make it unready."""
    required = request.app.state.readiness
    checks = {name: bool(check()) for name, check in required.items()}
    ok = all(checks.values())
    # Why a failed check failed, where it can say (the history store's inserts: since when, the error).
    reasons = failing_reasons(required, checks)
    checks.update({name: bool(check()) for name, check in
                   getattr(request.app.state, "advisory", {}).items()})
    return JSONResponse({"ok": ok, "checks": checks, **({"reasons": reasons} if reasons else {})},
                        status_code=200 if ok else 503)


@router.get("/metrics", operation_id="getMetrics", include_in_schema=False,
            dependencies=[Depends(METRICS)])
def metrics() -> Response:
    return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
