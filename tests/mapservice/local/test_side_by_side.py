"""Start-up steps side by side: they run at once, a failure is raised without waiting for
the steps still running, and a stack being stopped starts no process from a step still
running beside it."""

from __future__ import annotations

import threading
import time

import pytest

from mapservice.local.side_by_side import SideBySide
from mapservice.local.stack import Stack


@pytest.mark.parametrize("steps", [2, 3, 5])
def test_the_steps_run_at_once(steps):
    """Each step waits for all the others to have begun: one after another they never would."""
    all_begun = threading.Barrier(steps, timeout=10)
    done = []

    def step(i: int):
        return lambda: (all_begun.wait(), done.append(i))

    SideBySide().run(*(step(i) for i in range(steps)))
    assert sorted(done) == list(range(steps))


@pytest.mark.parametrize("failing", ["here", "elsewhere"])
def test_a_failure_is_raised_while_another_step_still_runs(failing):
    release = threading.Event()

    def blocked():
        release.wait(30)

    def fails():
        raise ValueError("this step failed")

    steps = SideBySide()
    started = time.monotonic()
    try:
        with pytest.raises(ValueError, match="this step failed"):
            if failing == "here":
                steps.run(fails, blocked)
            else:
                steps.run(lambda: None, blocked, fails)
        assert time.monotonic() - started < 10
    finally:
        release.set()
        steps.join(10)


def test_a_stopped_stack_starts_nothing_from_a_step_still_running(tmp_path):
    """A step that comes to spawn its component after `stop` began (its neighbour failed, or
    Ctrl-C) is refused: no process outlives the stack."""
    stack = Stack(tmp_path / "data", mqtt="mqtt://127.0.0.1:1", kafka="127.0.0.1:1")
    comes_late = threading.Event()
    refused: list[BaseException] = []

    def late():
        comes_late.wait(30)
        try:
            stack.spawn("late", "--help")
        except RuntimeError as exc:
            refused.append(exc)
            raise

    def fails():
        raise ValueError("a neighbour failed")

    with pytest.raises(ValueError):
        stack.side_by_side(fails, late)
    threading.Timer(0.5, comes_late.set).start()  # while `stop` waits for the steps
    stack.stop()
    assert "late" not in stack.procs
    assert refused and "being stopped" in str(refused[0])
    # Stopped, the stack starts again.
    proc = stack.spawn("again", "--help")
    assert proc.wait(60) == 0
    stack.stop()
