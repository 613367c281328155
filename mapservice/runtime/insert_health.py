"""Whether the history takes what the processors store: the truth about inserts.

A full disk (or ClickHouse refusing inserts for any other reason) leaves every read and
`SELECT 1` working while nothing new is stored; the processors retry (nothing is
acknowledged before it is stored) and recover by themselves once the inserts succeed
again. `InsertHealth` records that state for readiness (`history_store`: false with the
reason), the metrics and the replay UI's banner ("history not stored since ...").

The state is one flag's worth: failing since the first failed insert after a success,
storing again at the next success. A retry loop keeps trying for as long as it fails, so
the state cannot go stale while events wait.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

# ClickHouse ends an exception's message with its error code's name: "... (NOT_ENOUGH_SPACE)";
# over HTTP (`mapservice up`'s ClickHouse server) clickhouse-connect adds "(for url ...)".
_ERROR_CODE = re.compile(r"\(([A-Z][A-Z0-9_]{2,})\)(?:\s*\(for url [^)]*\))?\s*$")
# What an operator does about the usual refusals (ClickHouse's error code names).
HINTS = {
    "NOT_ENOUGH_SPACE": "free disk space where ClickHouse keeps its data",
    "CANNOT_WRITE_TO_FILE_DESCRIPTOR": "check the disk ClickHouse writes to (full or read-only?)",
    "TOO_MANY_PARTS": "ClickHouse merges fall behind the inserts; check its merges and disk",
    "MEMORY_LIMIT_EXCEEDED": "ClickHouse ran out of memory; raise its limit or lower the load",
    "READONLY": "the ClickHouse user or table is read-only",
    "TABLE_IS_READ_ONLY": "the table is read-only (a replica lost its keeper, or the disk failed)",
}
_MAX_ERROR_CHARS = 300


def error_code(error: str) -> str | None:
    """The ClickHouse error code's name at the end of `error`'s first line, if any."""
    match = _ERROR_CODE.search(error.strip().splitlines()[0] if error.strip() else "")
    return match.group(1) if match else None


def code_of(exc: BaseException) -> str | None:
    """The ClickHouse error code's name of a failed insert: as clickhouse-connect parsed it
    from an HTTP error's body (its `name`), else from the message's end."""
    name = getattr(exc, "name", None)
    if isinstance(name, str) and _ERROR_CODE.fullmatch(f"({name})"):
        return name
    return error_code(str(exc))


def describe(exc: BaseException) -> str:
    """One line about a failed insert: its ClickHouse error code first (when it has one),
    then the message, cut short."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    code = code_of(exc)
    text = text if len(text) <= _MAX_ERROR_CHARS else text[: _MAX_ERROR_CHARS - 3] + "..."
    return f"{code}: {text}" if code else f"{type(exc).__name__}: {text}"


class InsertHealth:
    """The state of the history's inserts in this process; thread-safe (the store thread
    writes it, probes and the API read it).

    Kept per kind of insert (`what`: the events, the dead letters, the derived views): a
    refusal of one table (TOO_MANY_PARTS on one, say) is not hidden by another's inserts
    succeeding in between. Failing while any kind fails, since the earliest of them.
    Callable as a readiness check (True while inserts succeed); `reason()` says why not.
    """

    def __init__(self, wall_s: Callable[[], float] = time.time) -> None:
        self.wall_s = wall_s
        self._lock = threading.Lock()
        self._failing_since: dict[
            str, float
        ] = {}  # per kind: its first failure since its last success
        self.failures = 0  # failed attempts since every kind last succeeded
        self.last_error: str | None = None
        self.last_error_code: str | None = None
        self.last_stored_s: float | None = None  # the last successful insert

    @property
    def failing_since_s(self) -> float | None:
        """The first failure of the current failure (None: nothing failing)."""
        with self._lock:
            return self._since()

    def _since(self) -> float | None:  # with the lock held
        return min(self._failing_since.values(), default=None)

    def stored(self, what: str = "events") -> float | None:
        """Records a successful insert; returns how long the history was not stored when
        this success ended that (None otherwise)."""
        with self._lock:
            since = self._since()
            self._failing_since.pop(what, None)
            self.last_stored_s = now = self.wall_s()
            if self._failing_since:
                return None
            self.failures, self.last_error, self.last_error_code = 0, None, None
            return None if since is None else now - since

    def failed(self, exc: BaseException, what: str = "events") -> bool:
        """Records a failed insert; returns whether it started a failure."""
        with self._lock:
            started = not self._failing_since
            self._failing_since.setdefault(what, self.wall_s())
            self.failures += 1
            self.last_error, self.last_error_code = describe(exc), code_of(exc)
            return started

    @property
    def failing(self) -> bool:
        return self.failing_since_s is not None

    def __call__(self) -> bool:
        """Readiness: the history takes inserts (or none was tried yet)."""
        return not self.failing

    def reason(self) -> str | None:
        """Why the history is not ready, with what to do; None while inserts succeed."""
        with self._lock:
            if (first := self._since()) is None:
                return None
            since = _utc_hms(first)
            hint = HINTS.get(self.last_error_code or "")
            attempts = f"{self.failures} attempt" + ("s" if self.failures != 1 else "")
            return (
                f"inserts failing since {since}Z ({attempts}): {self.last_error}"
                + (f"; {hint}" if hint else "")
                + "; the processors keep retrying and commit nothing unstored"
            )

    def status(self) -> dict[str, Any]:
        """For the API and the UI: storing or not, since when, why."""
        with self._lock:
            failing_since, last_stored = self._since(), self.last_stored_s
        return {
            "storing": failing_since is None,
            "failing_since_ms": None if failing_since is None else int(failing_since * 1000),
            "last_stored_ms": None if last_stored is None else int(last_stored * 1000),
            "reason": self.reason(),
        }


def _utc_hms(wall_s: float) -> str:
    return datetime.fromtimestamp(wall_s, UTC).strftime("%H:%M:%S")
