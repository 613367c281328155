"""A small HTTP endpoint for components without an API: /healthz (liveness), /readyz
(readiness) and /metrics. It runs in threads of its own, so it answers (with the truth)
even when the component's event loop is stuck."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from .metrics_gate import Refusal


def serve_health(
    host: str,
    port: int,
    status: Callable[[], dict],
    ready: Callable[[], dict] | None = None,
    metrics_gate: Callable[[str | None], Refusal] = lambda _auth: None,
    documents: dict[str, Callable[[], dict]] | None = None,
) -> ThreadingHTTPServer:
    """Starts a daemon thread; `status()` (liveness) and `ready()` (readiness, default:
    the liveness) return a dict with a boolean `ok`; `metrics_gate(authorization)` says
    whether /metrics may be served (see metrics_gate.py); `documents` maps further paths
    to what they answer as JSON (the processors' /history-status, for an API apart)."""
    paths = dict(documents or {})

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's naming
            refusal = (
                metrics_gate(self.headers.get("Authorization")) if self.path == "/metrics" else None
            )
            if refusal is not None:
                code, reason = refusal
                body, ctype = json.dumps({"detail": reason}).encode(), "application/json"
            elif self.path == "/metrics":
                body, ctype, code = generate_latest(), CONTENT_TYPE_LATEST, 200
            elif self.path in ("/healthz", "/readyz"):
                doc = (ready or status)() if self.path == "/readyz" else status()
                body = json.dumps(doc).encode()
                ctype, code = "application/json", 200 if doc.get("ok") else 503
            elif self.path in paths:
                body, ctype, code = json.dumps(paths[self.path]()).encode(), "application/json", 200
            else:
                body, ctype, code = (
                    b'{"detail":"use /healthz, /readyz or /metrics"}',
                    "application/json",
                    404,
                )
            self.send_response(code)
            if code == 401:
                self.send_header("WWW-Authenticate", 'Bearer realm="mapservice"')
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args) -> None:
            pass

    server = ThreadingHTTPServer((host, port), Handler)
    threading.Thread(target=server.serve_forever, name="health", daemon=True).start()
    return server
