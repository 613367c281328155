"""`mapservice up` killed with kill -9 at any moment of its start leaves no process behind:
its guard ends what it started, also a component it had started and not yet recorded (a
broker it was waiting for, a process just forked on a start thread). The moments are
generated from the start itself: the k-th trial kills `up` as soon as the k-th process it
started appears, for k = 1, 2, ... until a start completes first or the time is spent."""

from __future__ import annotations

import os
import signal
import time
import uuid

import pytest

from mapservice.local import lifetime
from tests.fixtures.up import UP_ENV, Up

pytestmark = [pytest.mark.long, pytest.mark.integration]

# Set in `up`'s environment, so every process it starts (and they start) inherits it: the
# processes of this test's `up`, whatever their command line.
RUN_VARIABLE = "UP_UNDER_TEST"
TRIALS_WITHIN_S = 60.0


def processes_of(run: str, up_pid: int) -> dict[int, str]:
    """Pid -> command line of the processes carrying this run's variable, but `up`."""
    return {
        pid: " ".join(lifetime.command_line(pid))[:160]
        for pid in lifetime.marked(run, RUN_VARIABLE)
        if pid != up_pid and lifetime.start_time(pid) is not None
    }


def kill_up_at_its_kth_process(data_dir, run: str, k: int) -> bool:
    """Starts `up` and kills it (SIGKILL) as soon as the k-th process it started shows;
    False if its start completed first (no k-th moment left), killed then all the same."""
    up = Up(
        data_dir,
        "--robots",
        "0",
        "--history-days",
        "0",
        env={**os.environ, **UP_ENV, RUN_VARIABLE: run},
        ready_within_s=None,
    )
    seen: set[int] = set()
    deadline = time.monotonic() + 120
    while len(seen) < k and time.monotonic() < deadline and up.proc.poll() is None:
        if "mapservice is up" in up.output:
            break
        seen |= set(processes_of(run, up.proc.pid))
        time.sleep(0.005)
    up.proc.kill()
    up.proc.wait(30)
    return len(seen) >= k


def survivors_after(run: str, timeout_s: float) -> dict[int, str]:
    """The processes of the run still there after its guard had `timeout_s` to end them."""
    deadline = time.monotonic() + timeout_s
    left = processes_of(run, 0)
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = processes_of(run, 0)
    return left


@pytest.mark.timeout(300)
def test_up_killed_at_any_moment_of_its_start_leaves_no_process_behind(tmp_path):
    data = tmp_path / "data"
    run = uuid.uuid4().hex
    trials_until = time.monotonic() + TRIALS_WITHIN_S
    k = 0
    try:
        while time.monotonic() < trials_until:
            k += 1
            moment_left = kill_up_at_its_kth_process(data, run, k)
            # Each component is given 10 s to stop by the guard, one after the other.
            left = survivors_after(run, 40)
            assert not left, f"up killed at the appearance of its process {k}: {left} outlived it"
            if not moment_left:
                break
        print(f"\nup killed at the appearance of each of its first {k} processes")
        assert k >= 3, "too few moments of the start were tried"
    finally:
        for pid in processes_of(run, 0):  # none if it passed; never leave them behind
            try:
                os.killpg(pid, signal.SIGKILL) if os.getpgid(pid) == pid else os.kill(pid, 9)
            except ProcessLookupError:
                pass
