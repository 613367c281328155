"""How `make test` runs its three steps: the `alone` tests with the fast tests beside them at
the lowest CPU priority (SCHED_IDLE), each on half of the ports, then the integration tests; every step
always runs and any failure fails the target. The recipe is run for real, by make, with a
stand-in for the venv's Python that records how each step was started."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from mapservice.local import embedded
from tests.fixtures.paths import ROOT

STEPS = {
    "fast": "not integration",
    "alone": "integration and alone",
    "integration": "integration and not alone",
}

RECORDER = textwrap.dedent(
    """\
    #!{python}
    import json, os, sys, time
    argv = sys.argv[1:]
    marks = argv[argv.index("-m", 1) + 1] if argv[:2] == ["-m", "pytest"] else None
    started = time.time()
    if marks is not None:
        time.sleep(1.0)
    with open(os.environ["RECORDED"], "a") as f:
        f.write(json.dumps({{"marks": marks, "policy": os.sched_getscheduler(0), "start": started,
                             "end": time.time(),
                             "slice": os.environ.get("MAPSERVICE_LOCAL_PORT_SLICE")}}) + "\\n")
    sys.exit(int(os.environ.get("FAIL_" + (marks or "").replace(" ", "_"), "0")))
    """
)


def run_make_test(tmp_path: Path, failing: str | None = None) -> tuple[int, dict[str, dict]]:
    python = tmp_path / "python"
    python.write_text(RECORDER.format(python=sys.executable))
    python.chmod(0o755)
    env = {**os.environ, "RECORDED": str(tmp_path / "steps.jsonl")}
    env.pop("MAPSERVICE_LOCAL_PORT_SLICE", None)
    if failing:
        env["FAIL_" + STEPS[failing].replace(" ", "_")] = "1"
    # The prerequisites (the venv, the system packages, the UI and its tests) are taken as
    # made: only the recipe of `test` runs.
    done = ["-o", ".venv/.installed", "-o", "system-deps", "-o", "ui", "-o", "test-ui"]
    result = subprocess.run(
        [
            "make",
            "--no-print-directory",
            "test",
            f"PY={python}",
            f"TEST_LOGS={tmp_path / 'logs'}",
            *done,
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    records = [json.loads(line) for line in (tmp_path / "steps.jsonl").read_text().splitlines()]
    steps = {name: r for r in records for name, marks in STEPS.items() if r["marks"] == marks}
    return result.returncode, steps


def test_the_fast_tests_run_beside_the_alone_tests_at_the_lowest_priority_on_other_ports(
    tmp_path: Path,
) -> None:
    code, steps = run_make_test(tmp_path)
    assert code == 0
    fast, alone, integration = steps["fast"], steps["alone"], steps["integration"]
    # This test may itself run at the lowest priority: the steps beside it start from its own.
    assert fast["policy"] == os.SCHED_IDLE
    assert alone["policy"] == integration["policy"] == os.sched_getscheduler(0)
    assert fast["start"] < alone["end"] and alone["start"] < fast["end"], (
        "the two steps ran one after the other"
    )
    assert integration["start"] >= max(fast["end"], alone["end"])
    assert {fast["slice"], alone["slice"]} == {"0/2", "1/2"}
    assert integration["slice"] is None


@pytest.mark.parametrize("failing", sorted(STEPS))
def test_a_failing_step_fails_the_target_and_every_step_still_runs(
    tmp_path: Path, failing: str
) -> None:
    code, steps = run_make_test(tmp_path, failing)
    assert code != 0
    assert set(steps) == set(STEPS)


@pytest.mark.parametrize("parts", [1, 2, 3, 4])
@pytest.mark.parametrize("runs", [1, 2, 3])
def test_every_worker_of_runs_side_by_side_chooses_from_ports_of_its_own(
    runs: int, parts: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    candidates = range(10_000, 65_536)
    slices = []
    for run in range(runs):
        run_slice = f"{run}/{runs}" if runs > 1 else None
        for part in range(parts):
            monkeypatch.setenv(embedded.PORT_SLICE_ENV, embedded.sub_slice(run_slice, part, parts))
            slices.append(set(embedded._slice(candidates)))
    assert all(len(s) >= len(candidates) // (runs * parts) - 1 for s in slices)
    assert sum(len(s) for s in slices) == len(set().union(*slices)), "two workers share ports"


@pytest.mark.parametrize("run_slice", [None, "", "2", "3/3", "-1/2", "a/b", "1/0"])
def test_a_missing_or_malformed_run_slice_is_cut_as_the_whole_range(run_slice: str | None) -> None:
    assert [embedded.sub_slice(run_slice, part, 3) for part in range(3)] == ["0/3", "1/3", "2/3"]


def test_ctrl_c_stops_a_test_run_started_in_the_background_by_a_shell(tmp_path: Path) -> None:
    """A shell without job control starts `&` commands with SIGINT ignored; the run must
    still stop on Ctrl-C (SIGINT to the terminal's process group), its fixtures torn down."""
    started, torn_down = tmp_path / "started", tmp_path / "torn-down"
    (tmp_path / "test_waits.py").write_text(
        textwrap.dedent(
            f"""\
            import pathlib, time
            import pytest

            @pytest.fixture
            def server():
                yield
                pathlib.Path({str(torn_down)!r}).touch()

            def test_waits(server):
                pathlib.Path({str(started)!r}).touch()
                time.sleep(60)
            """
        )
    )
    # The shell itself ignores SIGINT, as make's does while its recipe runs, and waits.
    run = f"{sys.executable} -m pytest -p no:cacheprovider -p tests.conftest -q {tmp_path / 'test_waits.py'}"
    command = f"trap '' INT; {run} & wait"
    shell = subprocess.Popen(["sh", "-c", command], cwd=ROOT, start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while not started.exists():
            assert time.monotonic() < deadline, "the test did not start"
            assert shell.poll() is None
            time.sleep(0.1)
        os.killpg(shell.pid, signal.SIGINT)
        shell.wait(timeout=20)
        assert torn_down.exists()
    finally:
        if shell.poll() is None:
            os.killpg(shell.pid, signal.SIGKILL)
            shell.wait()
