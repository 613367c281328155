"""Probes while a heavy request runs: does the server still answer the others?

`probe_during(probe_url, heavy)` sends `heavy` (any callable that makes one heavy request
and returns what the test wants to check, e.g. the reply) on a thread of its own and, until
it returns, GETs `probe_url` (a liveness probe: /healthz, /ping) every `interval_s`,
timing each answer. The run's figures and the machine's load average (before and after)
are printed, so they land in the test's output; `assert_responsive` fails with them.

A server that does the heavy work on its event loop answers no probe until the work is
done: the probes' worst time is then about the heavy request's.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import httpx

T = TypeVar("T")

MAX_PROBE_S = 1.0  # a liveness probe's answer, however heavy the other requests


@dataclass
class ProbedRun(Generic[T]):
    label: str
    result: T | None = None
    error: BaseException | None = None
    heavy_s: float = 0.0
    probe_s: list[float] = field(default_factory=list)
    probe_failures: list[str] = field(default_factory=list)
    load_before: tuple[float, float, float] = (0.0, 0.0, 0.0)
    load_after: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def worst_probe_s(self) -> float:
        return max(self.probe_s, default=0.0)

    def summary(self) -> str:
        load = " ".join(f"{x:.2f}" for x in self.load_before)
        load_after = " ".join(f"{x:.2f}" for x in self.load_after)
        return (
            f"{self.label}: heavy request {self.heavy_s:.3f} s; {len(self.probe_s)} probes, "
            f"worst {self.worst_probe_s:.3f} s, failures {self.probe_failures or 'none'}; "
            f"load average {load} before, {load_after} after ({os.cpu_count()} CPUs)"
        )

    def assert_responsive(self, max_heavy_s: float, max_probe_s: float = MAX_PROBE_S) -> T:
        """The heavy request's result, once it is known that it came back within
        `max_heavy_s` and every probe within `max_probe_s`."""
        if self.error is not None:
            raise AssertionError(f"the heavy request failed: {self.summary()}") from self.error
        assert not self.probe_failures, self.summary()
        assert self.worst_probe_s <= max_probe_s, self.summary()
        assert self.heavy_s <= max_heavy_s, self.summary()
        return self.result  # type: ignore[return-value]


def probe_during(
    probe_url: str | Sequence[str],
    heavy,
    *,
    label: str = "heavy request",
    interval_s: float = 0.1,
    probe_timeout_s: float = 10.0,
    heavy_timeout_s: float = 120.0,
) -> ProbedRun:
    """Runs `heavy()` on a thread while probing `probe_url` every `interval_s` (module
    docstring). A probe that does not answer 200 within `probe_timeout_s` is a failure;
    `heavy` not returning within `heavy_timeout_s` is an error of the run. Several probe
    URLs (liveness and readiness) are asked in turn, each every `interval_s`."""
    urls = [probe_url] if isinstance(probe_url, str) else list(probe_url)
    run: ProbedRun = ProbedRun(label, load_before=os.getloadavg())
    done = threading.Event()

    def send() -> None:
        started = time.monotonic()
        try:
            run.result = heavy()
        except BaseException as exc:  # reported by assert_responsive
            run.error = exc
        finally:
            run.heavy_s = time.monotonic() - started
            done.set()

    thread = threading.Thread(target=send, name=f"heavy: {label}", daemon=True)
    with httpx.Client(timeout=probe_timeout_s) as probes:
        for url in urls:
            probes.get(url)  # connected before the heavy request starts
        thread.start()
        deadline = time.monotonic() + heavy_timeout_s
        while not done.is_set():
            if time.monotonic() > deadline:
                run.error = TimeoutError(f"no answer within {heavy_timeout_s} s")
                break
            round_started = time.monotonic()
            for url in urls:
                started = time.monotonic()
                try:
                    status = probes.get(url).status_code
                    if status != 200:
                        run.probe_failures.append(f"{url}: status {status}")
                except httpx.HTTPError as exc:
                    run.probe_failures.append(f"{url}: {type(exc).__name__}: {exc}")
                run.probe_s.append(time.monotonic() - started)
            done.wait(max(0.0, interval_s - (time.monotonic() - round_started)))
    thread.join(timeout=1)
    run.load_after = os.getloadavg()
    print(run.summary())
    return run
