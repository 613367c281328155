"""Restarts the components of `mapservice up` that exit, with exponential backoff.

A component that exits (a crash, an OOM kill, a map the simulator cannot use) must not take
the others down: the supervisor notices it, waits `backoff_s(failures)` and starts it again
through the restart function it was given, and reports each step through `report`. A
component that stayed up for `healthy_after_s` counts as healthy again (its backoff resets).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import structlog

log = structlog.get_logger(__name__)


def backoff_s(failures: int, base_s: float = 1.0, cap_s: float = 60.0) -> float:
    """1, 2, 4, ... seconds after the 1st, 2nd, 3rd failure in a row, at most `cap_s`."""
    return min(cap_s, base_s * 2.0 ** max(0, failures - 1))


@dataclass
class _Watched:
    restart: Callable[[], object]
    failures: int = 0
    started_at: float = 0.0
    restart_at: float | None = None  # set while waiting to restart


@dataclass
class Supervisor:
    """`is_alive(name)` says whether a component runs; `restarts` maps a name to the function
    that starts it again (it raises when that fails; the supervisor then backs off more)."""

    is_alive: Callable[[str], bool]
    restarts: dict[str, Callable[[], object]]
    report: Callable[[str], None] = lambda message: None
    clock: Callable[[], float] = time.monotonic
    base_s: float = 1.0
    cap_s: float = 60.0
    healthy_after_s: float = 60.0
    watched: dict[str, _Watched] = field(default_factory=dict)

    def __post_init__(self) -> None:
        now = self.clock()
        self.watched = {name: _Watched(fn, started_at=now) for name, fn in self.restarts.items()}

    def check(self) -> None:
        """One pass: notice exits, restart those whose backoff has passed."""
        now = self.clock()
        for name, w in self.watched.items():
            if w.restart_at is None:
                if self.is_alive(name):
                    if w.failures and now - w.started_at >= self.healthy_after_s:
                        w.failures = 0
                    continue
                w.failures += 1
                w.restart_at = now + backoff_s(w.failures, self.base_s, self.cap_s)
                self._say(
                    f"{name} exited; restarting it in {w.restart_at - now:.0f} s "
                    f"(failure {w.failures} in a row)",
                    name,
                    w.failures,
                )
            elif now >= w.restart_at:
                try:
                    w.restart()
                except Exception as exc:  # noqa: BLE001 - any failure to start: back off more
                    w.failures += 1
                    w.restart_at = self.clock() + backoff_s(w.failures, self.base_s, self.cap_s)
                    self._say(
                        f"{name} did not start again ({exc}); next try in "
                        f"{w.restart_at - self.clock():.0f} s",
                        name,
                        w.failures,
                    )
                    continue
                w.restart_at, w.started_at = None, self.clock()
                self._say(f"{name} restarted", name, w.failures)

    def _say(self, message: str, name: str, failures: int) -> None:
        log.warning(message, component=name, failures=failures)
        self.report(message)
