"""`bench ingest --profile DIR`: py-spy samples each Python component of the stack while the
fleet runs and writes one flame graph per component and run, named so that the runs of a
comparison do not overwrite each other."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from argparse import Namespace
from pathlib import Path

import pytest

from mapservice.bench.ingest.profile import (
    Profilers,
    profile_path,
    python_components,
    start_profilers,
)

BUSY = textwrap.dedent(
    """
    import sys, time
    def spin_in_a_function_named_for_the_test():
        end = time.monotonic() + 30
        while time.monotonic() < end:
            sum(range(1000))
    print("ready", flush=True)
    spin_in_a_function_named_for_the_test()
    """
)


def _busy_process() -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", BUSY], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


@pytest.mark.timeout(60)
def test_each_component_gets_a_flame_graph_naming_where_its_cpu_went(tmp_path) -> None:
    """Two Python processes sampled for two seconds: a file each, named by component and
    run, showing the function that burned the CPU."""
    procs = {"gateway": _busy_process(), "server": _busy_process()}
    try:
        profilers = Profilers(tmp_path, {n: p.pid for n, p in procs.items()}, 2, "run3")
        profilers.start()
        written = profilers.wait()
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
    assert written == {n: str(tmp_path / f"{n}-run3.svg") for n in procs}
    for name in procs:
        svg = profile_path(tmp_path, name, "run3").read_text()
        assert svg.startswith("<?xml") and "spin_in_a_function_named_for_the_test" in svg
    assert not list(tmp_path.glob("*.log")), "py-spy's error log kept though it succeeded"


@pytest.mark.timeout(60)
def test_a_process_that_cannot_be_sampled_is_reported_not_fatal(tmp_path) -> None:
    """A pid that is gone: the run goes on, and the result says the file was not written
    and where py-spy's message is."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    profilers = Profilers(tmp_path, {"server": gone.pid}, 1, "run1")
    profilers.start()
    written = profilers.wait()
    assert written["server"].startswith("not written") and "server-run1.log" in written["server"]
    assert (tmp_path / "server-run1.log").read_text().strip()


class _Proc:
    def __init__(self, pid: int, alive: bool = True) -> None:
        self.pid = pid
        self._alive = alive

    def poll(self):
        return None if self._alive else 0


class _Stack:
    """The parts of a Stack the profilers read: its processes and what it spawned itself."""

    def __init__(self) -> None:
        self.procs = {
            "kafka": _Proc(10),
            "mqtt": _Proc(11),
            "server": _Proc(12),
            "gateway": _Proc(13),
            "gateway-2": _Proc(14, alive=False),
        }
        self.commands = {"server": ("serve",), "gateway": ("gateway",), "gateway-2": ("gateway",)}


def test_only_the_running_python_components_are_sampled() -> None:
    """The brokers (Java, C) are not Python; a component that exited has no process."""
    assert python_components(_Stack()) == {"server": 12, "gateway": 13}


@pytest.mark.parametrize(
    "variant, run, name", [("", 2, "server-run2.svg"), ("main", 1, "server-main-run1.svg")]
)
def test_a_comparisons_runs_are_named_by_variant(tmp_path, monkeypatch, variant, run, name) -> None:
    started: list[Profilers] = []
    monkeypatch.setattr(Profilers, "start", lambda self: started.append(self))
    args = Namespace(profile=str(tmp_path), variant_name=variant, seconds=30)
    profilers = start_profilers(args, _Stack(), run)
    assert profilers is started[0]
    assert profile_path(Path(profilers.directory), "server", profilers.label).name == name
    assert profilers.seconds == 30


def test_without_profile_nothing_is_sampled() -> None:
    assert start_profilers(Namespace(profile=None, seconds=30), _Stack(), 1) is None
