"""`mapservice bench foxglove`'s clients: Foxglove's own npm client (@foxglove/ws-protocol,
the one the integration test uses) in one node process (tests/foxglove_client/bench.mjs),
driven by JSON lines on its stdin; its JSON lines are collected as they come. Its packages
are installed with `npm ci` the first time (the lock file pins them)."""

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
from typing import IO, Any

from mapservice.local.checkout import FOXGLOVE_CLIENT_DIR

Event = dict[str, Any]
NPM_CI_TIMEOUT_S = 300


def ensure_installed(directory: Path = FOXGLOVE_CLIENT_DIR) -> None:
    """node and the client's npm packages, installed by `npm ci` when missing or older than
    the lock file; a SystemExit saying what is missing otherwise."""
    npm, node = shutil.which("npm"), shutil.which("node")
    if npm is None or node is None:
        raise SystemExit("bench foxglove: node and npm are needed (Node.js >= 20)")
    marker = directory / "node_modules" / ".package-lock.json"
    lock = directory / "package-lock.json"
    if marker.exists() and marker.stat().st_mtime >= lock.stat().st_mtime:
        return
    done = subprocess.run(
        [npm, "ci", "--no-audit", "--no-fund"],
        cwd=directory,
        capture_output=True,
        text=True,
        timeout=NPM_CI_TIMEOUT_S,
    )
    if done.returncode != 0:
        raise SystemExit(f"bench foxglove: npm ci in {directory} failed: {done.stderr[-2000:]}")


class NodeClients:
    """`node bench.mjs MODE URL ARGS...`: `events` grows as it prints; `send` a command."""

    def __init__(self, mode: str, url: str, *args: str, log_path: Path | None = None) -> None:
        ensure_installed()
        if log_path:
            log_path.parent.mkdir(parents=True, exist_ok=True)
        self.stderr: IO[bytes] | None = open(log_path, "ab") if log_path else None
        self.proc = subprocess.Popen(
            ["node", "bench.mjs", mode, url, *args],
            cwd=FOXGLOVE_CLIENT_DIR,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.stderr or subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
        self.events: list[Event] = []
        self._changed = threading.Condition()
        threading.Thread(target=self._read, name="foxglove-clients", daemon=True).start()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            event = json.loads(line)
            with self._changed:
                self.events.append(event)
                self._changed.notify_all()
        with self._changed:
            self.events.append({"event": "exited"})
            self._changed.notify_all()

    def send(self, **command: Any) -> int:
        """Sends a command; returns how many events came before it (for `wait_for`)."""
        with self._changed:
            seen = len(self.events)
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()
        return seen

    def wait_for(self, matches: Callable[[Event], bool], timeout_s: float, after: int = 0) -> Event:
        """The first event from index `after` on that `matches`; a RuntimeError after
        `timeout_s` or when the clients exited."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                for event in self.events[after:]:
                    if matches(event):
                        return event
                left = deadline - time.monotonic()
                if left <= 0 or (self.events and self.events[-1]["event"] == "exited"):
                    raise RuntimeError(
                        f"the Foxglove clients sent no such event within {timeout_s:.0f} s "
                        f"(last: {self.events[-3:]})"
                    )
                self._changed.wait(left)

    def last(self, kind: str) -> Event | None:
        with self._changed:
            return next((e for e in reversed(self.events) if e["event"] == kind), None)

    def closed(self) -> list[Event]:
        """The clients' connections that closed (refused or dropped by the server)."""
        with self._changed:
            return [e for e in self.events if e["event"] == "closed"]

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.send(op="close")
                self.proc.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        if self.stderr is not None:
            self.stderr.close()

    def __enter__(self) -> NodeClients:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
