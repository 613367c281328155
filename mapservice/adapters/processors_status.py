"""The history's state as processors running in another process report it.

The inserts' truth (mapservice/runtime/insert_health.py) lives where the processors run.
An API process apart from them (`mapservice up`, which runs each in its own process)
asks their health endpoint's /history-status for it, so that its /readyz and the replay
UI's banner ("history not stored since ...") say what `serve` says in one process.

Asked at most every `ttl_s`, each call bounded by `timeout_s` (a probe never waits on the
processors longer: runtime.health.CachedCheck). Processors that do not answer count as
not storing, since the first failed call, with the reason.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import httpx

from mapservice.runtime.health import CachedCheck

STATUS_PATH = "/history-status"


class ProcessorsStatus:
    """Readiness check (callable, with `reason()`) and `status()` for /api/v1/status."""

    def __init__(
        self,
        base_url: str,
        ttl_s: float = 1.0,
        timeout_s: float = 1.0,
        wall_s: Callable[[], float] = time.time,
    ) -> None:
        self.url = base_url.rstrip("/") + STATUS_PATH
        self.timeout_s, self.wall_s = timeout_s, wall_s
        self._lock = threading.Lock()
        self._doc: dict[str, Any] | None = None
        self._unreachable_since_s: float | None = None
        self._check = CachedCheck("history_store", self._fetch, ttl_s=ttl_s, timeout_s=timeout_s)

    def _fetch(self) -> bool:
        try:
            reply = httpx.get(self.url, timeout=self.timeout_s)
            reply.raise_for_status()
            doc = reply.json()
            storing = bool(doc["storing"])
        except (httpx.HTTPError, ValueError, KeyError, TypeError) as exc:
            with self._lock:
                self._unreachable_since_s = self._unreachable_since_s or self.wall_s()
                last = (self._doc or {}).get("last_stored_ms")
                self._doc = {
                    "storing": False,
                    "failing_since_ms": int(self._unreachable_since_s * 1000),
                    "last_stored_ms": last,
                    "reason": (
                        f"the processors do not answer at {self.url} "
                        f"({type(exc).__name__}: {str(exc)[:200]}); nothing new is "
                        "stored until they run again (see their log)"
                    ),
                }
            return False
        with self._lock:
            self._doc, self._unreachable_since_s = doc, None
        return storing

    def __call__(self) -> bool:
        return self._check()

    def nowait(self) -> bool | None:
        """The answer without waiting (the API's probes call it on the event loop)."""
        return self._check.nowait()

    def status(self) -> dict[str, Any]:
        """storing, failing_since_ms, last_stored_ms, reason (insert_health's shape)."""
        self._check()
        with self._lock:
            if self._doc is not None:
                return dict(self._doc)
        return {
            "storing": False,
            "failing_since_ms": None,
            "last_stored_ms": None,
            "reason": f"no answer from the processors at {self.url} yet",
        }

    def reason(self) -> str | None:
        with self._lock:
            return None if self._doc is None else self._doc.get("reason")
