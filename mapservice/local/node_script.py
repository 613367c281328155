"""A node script of the checkout as a process: its npm packages installed by `npm ci` (from
its pinned lock file) the first time and again when the lock file changes; each JSON line it
prints collected as an event, commands sent to it as JSON lines on its stdin. The tests'
Foxglove and VDA 5050 clients and `mapservice bench foxglove` run their node scripts so."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, Self

Event = dict[str, Any]
NPM_CI_TIMEOUT_S = 300


class NodeMissing(RuntimeError):
    """node or npm is not installed."""


class NoSuchEvent(AssertionError):
    """The script printed no such event in time (an assertion of the tests that wait)."""


def npm_ci_if_stale(directory: Path, timeout_s: float = NPM_CI_TIMEOUT_S) -> None:
    """`npm ci` in `directory` unless its packages are installed from its current lock file;
    NodeMissing without node and npm, RuntimeError if the install fails."""
    npm, node = shutil.which("npm"), shutil.which("node")
    if npm is None or node is None:
        raise NodeMissing("node and npm are needed (Node.js >= 20 with npm)")
    marker = directory / "node_modules" / ".package-lock.json"
    lock = directory / "package-lock.json"
    if marker.exists() and marker.stat().st_mtime >= lock.stat().st_mtime:
        return
    done = subprocess.run(
        [npm, "ci", "--no-audit", "--no-fund"],
        cwd=directory,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    if done.returncode != 0:
        raise RuntimeError(
            f"npm ci in {directory} failed ({done.returncode}): {done.stderr[-2000:]}"
        )


class NodeScript:
    """`node SCRIPT ARGS...` in `directory` (its packages installed); `events` grows as it
    prints, each stamped with its arrival (`at`, monotonic seconds). Its stderr goes to
    `stderr` (a file), or a temporary file when None."""

    def __init__(
        self, directory: Path, script: str, *args: str, stderr: IO[bytes] | None = None
    ) -> None:
        import tempfile

        npm_ci_if_stale(directory)
        self.stderr: IO[bytes] = stderr if stderr is not None else tempfile.TemporaryFile()
        self.proc = subprocess.Popen(
            ["node", script, *args],
            cwd=directory,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.stderr,
            text=True,
            start_new_session=True,
        )
        self.events: list[Event] = []
        self._changed = threading.Condition()
        threading.Thread(target=self._read, name=f"node-{script}", daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            event = json.loads(line)
            event["at"] = time.monotonic()
            with self._changed:
                self.events.append(event)
                self._changed.notify_all()
        with self._changed:
            self.events.append({"event": "exited", "at": time.monotonic()})
            self._changed.notify_all()

    def send(self, **command: Any) -> int:
        """Sends a command; returns how many events came before it (for `wait_for`'s after)."""
        with self._changed:
            seen = len(self.events)
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()
        return seen

    def wait_for(self, matches: Callable[[Event], bool], timeout_s: float, after: int = 0) -> Event:
        """The first event from index `after` on that `matches`, waiting up to `timeout_s`;
        NoSuchEvent (naming the last events and the script's stderr) when none came in
        time or the script exited."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                for event in self.events[after:]:
                    if matches(event):
                        return event
                left = deadline - time.monotonic()
                if left <= 0 or (self.events and self.events[-1]["event"] == "exited"):
                    raise NoSuchEvent(
                        f"no such event within {timeout_s} s; last events: {self.events[-5:]}; "
                        f"stderr: {self.stderr_text()[-1500:]}"
                    )
                self._changed.wait(left)

    def last(self, kind: str) -> Event | None:
        """The latest event of this kind."""
        with self._changed:
            return next((e for e in reversed(self.events) if e["event"] == kind), None)

    def stderr_text(self) -> str:
        try:
            self.stderr.flush()
            self.stderr.seek(0)
            return self.stderr.read().decode(errors="replace")
        except (OSError, ValueError):  # a log file opened for appending only, or closed
            return ""

    def close(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self.stderr.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
