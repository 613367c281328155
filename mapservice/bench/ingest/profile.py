"""`bench ingest --profile DIR`: a py-spy flame graph of each of the stack's Python components
(the gateway replicas, `serve`) while the fleet runs, one SVG per component and run.

py-spy samples another process from outside (ptrace, root or CAP_SYS_PTRACE), so the code
under test is not changed; `--nonblocking` reads the process without stopping it, which
keeps what the sampler costs out of the component's own CPU figure. Idle threads are left
out: a flame graph shows where CPU is spent, not where threads wait.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from argparse import Namespace
from pathlib import Path
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from mapservice.local.stack import Stack

SAMPLES_PER_S = 100  # py-spy's default: 6,000 samples in a 60-second run


def py_spy() -> str:
    """The py-spy executable beside this Python, else on PATH; exits with a clear error where
    there is none."""
    beside = Path(sys.executable).parent / "py-spy"
    found = str(beside) if beside.is_file() else shutil.which("py-spy")
    if not found:
        sys.exit("--profile needs py-spy (pip install py-spy; the test extra installs it)")
    return found


def profile_path(directory: Path, component: str, label: str) -> Path:
    """Where a component's flame graph of one run goes: `<component>-<label>.svg`."""
    return directory / f"{component}-{label}.svg"


class Profilers:
    """py-spy recording each Python component of a stack for `seconds`."""

    def __init__(self, directory: Path, pids: dict[str, int], seconds: float, label: str) -> None:
        self.directory = directory
        self.pids = pids
        self.seconds = seconds
        self.label = label
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(self) -> None:
        exe = py_spy()
        self.directory.mkdir(parents=True, exist_ok=True)
        for component, pid in self.pids.items():
            out = profile_path(self.directory, component, self.label)
            with open(out.with_suffix(".log"), "wb") as errors:
                self.procs[component] = self._record(exe, pid, out, errors)

    def _record(self, exe: str, pid: int, out: Path, errors: IO[bytes]) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [
                exe,
                "record",
                "--pid",
                str(pid),
                "--duration",
                str(max(1, round(self.seconds))),
                "--rate",
                str(SAMPLES_PER_S),
                "--nonblocking",
                # one frame per function, not per line: a graph a tenth the size that
                # still names every function the time went to
                "--function",
                "--format",
                "flamegraph",
                "--output",
                str(out),
            ],
            stdout=subprocess.DEVNULL,
            stderr=errors,
        )

    def wait(self, timeout_s: float = 60) -> dict[str, str]:
        """Waits for each recording to be written; returns component -> file (or the error)."""
        written: dict[str, str] = {}
        for component, proc in self.procs.items():
            out = profile_path(self.directory, component, self.label)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            log = out.with_suffix(".log")
            if out.is_file():
                written[component] = str(out)
                log.unlink(missing_ok=True)
            else:
                written[component] = f"not written (py-spy exit {proc.returncode}; see {log})"
        return written


def start_profilers(args: Namespace, stack: Stack, run: int) -> Profilers | None:
    """With `--profile DIR`: py-spy started on each Python component for the fleet's run."""
    directory = getattr(args, "profile", None)
    if not directory:
        return None
    variant = getattr(args, "variant_name", "")
    label = f"{variant}-run{run}" if variant else f"run{run}"
    profilers = Profilers(Path(directory), python_components(stack), args.seconds, label)
    profilers.start()
    return profilers


def python_components(stack: Stack) -> dict[str, int]:
    """The stack's components that run Python (those it spawned as `mapservice ...`), by pid."""
    return {
        name: proc.pid
        for name, proc in stack.procs.items()
        if name in stack.commands and proc.poll() is None
    }
