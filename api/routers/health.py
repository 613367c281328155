"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="getLiveness")
def liveness() -> dict:
    return {"ok": True}


@router.get("/readyz", operation_id="getReadiness")
def readiness(request: Request) -> JSONResponse:
    checks = {name: bool(check()) for name, check in request.app.state.readiness.items()}
    ok = all(checks.values())
    return JSONResponse({"ok": ok, "checks": checks}, status_code=200 if ok else 503)


@router.get("/metrics", operation_id="getMetrics", include_in_schema=False)
def metrics() -> Response:
    return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
