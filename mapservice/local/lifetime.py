"""The processes of `mapservice up` live no longer than `up` itself.

Each component runs in a session of its own (Ctrl-C in a terminal reaches `up` alone, which
then stops them in order). So that a `kill -9` of `up` does not leave them running:

- `up` records itself and every component (pid, start time, command) in a pid file in the
  data dir;
- a guard process, in a session of its own, is started with the parent-death signal set
  (Linux `PR_SET_PDEATHSIG`): when `up` dies, for any reason, the guard gets SIGTERM and
  stops the recorded components in `up`'s own order (the gateway before the processors,
  the brokers last: all at once, tansu's memory went before the processors had read the
  last messages from it, and acknowledged messages were lost);
- the next `up` on that data dir ends whatever the record names that still runs (the guard
  killed too, a machine where the signal cannot be set), in the same order, by recorded
  process group only, and only a process whose start time and command line are still the
  recorded ones (a reused pid is someone else's);
- a process is recorded only once started, so one that `up` (or a start thread of it)
  had just forked when it died is in no record: every process `up` starts carries `up`'s
  mark in its environment (MARK_ENV: `up`'s pid and start time, which no other process
  shares), and the guard and the next `up` also end the processes that carry the dead
  `up`'s mark and are not recorded, first (they were just starting: nothing in flight).
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
PID_FILE = "up.pids.json"
GUARD = "guard"
# A process carrying the mark of a dead `up` that its record does not name: it was being
# started when `up` died.
UNRECORDED = "unrecorded"
MARK_ENV = "MAPSERVICE_UP_MARK"
# Stack.stop's order: who feeds a broker stops before it, the brokers last.
STOP_ORDER = (
    GUARD,
    UNRECORDED,
    "sim",
    "gateway",
    "server",
    "api",
    "processors",
    "clickhouse",
    "mqtt",
    "kafka",
)


def stop_rank(name: str) -> int:
    """Where component `name` stops in STOP_ORDER: a replica ("gateway-2", "processors-1")
    with its kind, before the brokers it needs to shut down cleanly; other names last."""
    kind = name if name in STOP_ORDER else name.rsplit("-", 1)[0]
    return STOP_ORDER.index(kind) if kind in STOP_ORDER else len(STOP_ORDER)


def _prctl():
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux: the pid file still covers it
        return None


_PRCTL = _prctl()


def private_files() -> None:
    """A `preexec_fn`: the child creates files no one else may read (umask 077: secrets,
    logs, the broker's store, the history)."""
    os.umask(0o077)


def die_with_parent() -> None:
    """A `preexec_fn`: as private_files, and the child gets SIGTERM when the process that
    started it dies. Only from a process's main thread: Linux sends the signal when the
    thread that forked the child ends, which for another thread is long before the process."""
    os.umask(0o077)
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def guard_preexec() -> None:
    """The guard's `preexec_fn`: as die_with_parent, with SIGTERM blocked (a blocked signal
    stays blocked across exec, and pending): `up` killed while the guard's interpreter
    starts would otherwise end the guard before it acted; blocked, the signal waits for the
    guard to take it."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    die_with_parent()


def start_time(pid: int) -> int | None:
    """The process's start time in clock ticks since boot (/proc/<pid>/stat field 22), None
    when it does not run (or is a zombie: it runs nothing any more)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    if fields[0] == "Z":
        return None
    return int(fields[19])


def mark_of(pid: int, start: int | None) -> str:
    """The mark of the `up` with this pid and start time (MARK_ENV's value)."""
    return f"{pid}:{start}"


def mark_children() -> str:
    """Every process this one starts from now on carries its mark (MARK_ENV); returns it.
    Through the environment, so also what is started without an environment of its own
    (the brokers inherit this process's)."""
    mark = mark_of(os.getpid(), start_time(os.getpid()))
    os.environ[MARK_ENV] = mark
    return mark


def marked(mark: str, variable: str = MARK_ENV) -> list[int]:
    """The pids of the processes (of this user: others' environments are not readable)
    whose environment sets `variable` to `mark`. A child forked and not yet executing its
    program shows its parent's environment as it was at the parent's start: found once it
    runs."""
    needle = f"\0{variable}={mark}\0".encode()
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = b"\0" + (entry / "environ").read_bytes()
        except OSError:  # gone meanwhile, or another user's
            continue
        if needle in environ:
            pids.append(int(entry.name))
    return pids


def command_line(pid: int) -> list[str]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [part.decode(errors="replace") for part in raw.split(b"\0") if part]


@dataclass(frozen=True)
class Recorded:
    """A process as the pid file saw it started."""

    name: str
    pid: int
    start: int | None
    command: tuple[str, ...]

    @classmethod
    def of(cls, name: str, pid: int) -> Recorded:
        return cls(name, pid, start_time(pid), tuple(command_line(pid)))

    def still_running(self) -> bool:
        """Whether this very process still runs: same pid, start time and command line."""
        return (
            self.start is not None
            and start_time(self.pid) == self.start
            and tuple(command_line(self.pid)) == self.command
        )


@dataclass
class PidFile:
    """DATA_DIR/up.pids.json: the `up` that runs on this data dir and its components."""

    path: Path

    @classmethod
    def in_data_dir(cls, data_dir: Path) -> PidFile:
        return cls(Path(data_dir) / PID_FILE)

    def write(self, pids: dict[str, int]) -> None:
        """Records this process as `up` and `pids` (component name -> pid) as its components;
        a component's start time is read now (it was just started, by this process)."""
        known = {r.name: r for r in self._read()[1] if r.name in pids and r.pid == pids[r.name]}
        components = [known.get(name) or Recorded.of(name, pid) for name, pid in pids.items()]
        record = {
            "up": _as_json(Recorded.of("up", os.getpid())),
            "components": [_as_json(r) for r in components if r.start is not None],
        }
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        tmp.parent.mkdir(parents=True, exist_ok=True)
        with open(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as file:
            json.dump(record, file)
        os.replace(tmp, self.path)

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)

    def _read(self) -> tuple[Recorded | None, list[Recorded]]:
        try:
            record = json.loads(self.path.read_text())
            return (_from_json(record["up"]), [_from_json(r) for r in record["components"]])
        except (OSError, ValueError, KeyError, TypeError):
            return None, []  # none, or unreadable: nothing to trust in it

    def running_up(self) -> Recorded | None:
        """The recorded `up`, if it still runs (another `up` on this data dir)."""
        up, _ = self._read()
        return up if up is not None and up.pid != os.getpid() and up.still_running() else None

    def leftovers(self) -> list[Recorded]:
        """Components still running although their `up` does not: recorded ones, and those
        carrying its mark that were being started when it died."""
        up, _ = self._read()
        if up is None or self.running_up() is not None:
            return []
        return self.unrecorded(mark_of(up.pid, up.start)) + self.running_components()

    def running_components(self) -> list[Recorded]:
        return [r for r in self._read()[1] if r.still_running() and r.pid != os.getpid()]

    def unrecorded(self, mark: str) -> list[Recorded]:
        """The processes carrying `mark` that the record does not name (nor this process)."""
        recorded = {r.pid for r in self._read()[1]}
        return [
            Recorded.of(UNRECORDED, pid)
            for pid in marked(mark)
            if pid not in recorded and pid != os.getpid()
        ]


def end(leftovers: list[Recorded], timeout_s: float = 10.0) -> None:
    """Ends the leftovers one by one in STOP_ORDER (a guard still at work is given the time
    to finish first): SIGTERM to its process group (each component leads its own session; a
    stopped one is continued, to act on it), SIGKILL if it still runs after `timeout_s`."""

    for process in sorted(leftovers, key=lambda process: stop_rank(process.name)):
        if process.name == GUARD:
            _wait_gone(process, timeout_s * len(leftovers))
        for sig in (signal.SIGTERM, signal.SIGKILL):
            if not process.still_running():
                break
            _signal_group(process, sig)
            _signal_group(process, signal.SIGCONT)
            _wait_gone(process, timeout_s)


def _wait_gone(process: Recorded, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while process.still_running() and time.monotonic() < deadline:
        time.sleep(0.05)


# How long the guard keeps looking for `up`'s unrecorded children after it found the last
# one: a child forked just before `up` died shows the mark only once it runs its program,
# which on a loaded machine can be seconds later.
SETTLE_S = 10.0


def guard(pid_file: Path, parent: int, mark: str, settle_s: float = SETTLE_S) -> None:
    """The guard's life: wait for SIGTERM (its parent `up` died: the parent-death signal),
    then end what `up` started, in order: what the pid file names, and what carries `up`'s
    `mark` unrecorded; then again each unrecorded one that turns up, until none has for
    `settle_s`. `up` ends the guard with SIGKILL after it stopped its components itself."""
    # SIGTERM is taken by sigtimedwait, not by a handler: Python runs a handler between
    # any two bytecodes of the main thread, also while that thread holds the lock the
    # handler needs (an Event's, at the start and end of its wait), and the guard then
    # waited for itself for ever, leaving all of `up`'s components running.
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is `up`'s to act on
    while signal.sigtimedwait({signal.SIGTERM}, 1.0) is None:
        if os.getppid() != parent:  # `up` died before it set the parent-death signal
            break
    record = PidFile(pid_file)
    end(record.unrecorded(mark) + record.running_components())
    quiet_until = time.monotonic() + settle_s
    while time.monotonic() < quiet_until:
        time.sleep(0.2)
        unrecorded = record.unrecorded(mark)
        if unrecorded:
            end(unrecorded)
            quiet_until = time.monotonic() + settle_s


def _signal_group(process: Recorded, sig: int) -> None:
    try:
        if os.getpgid(process.pid) == process.pid:
            os.killpg(process.pid, sig)
        else:  # not a group leader (not started by a stack): that process alone
            os.kill(process.pid, sig)
    except ProcessLookupError:
        pass


def _as_json(r: Recorded) -> dict:
    return {"name": r.name, "pid": r.pid, "start": r.start, "command": list(r.command)}


def _from_json(d: dict) -> Recorded:
    return Recorded(str(d["name"]), int(d["pid"]), d["start"], tuple(d["command"]))


if __name__ == "__main__":
    if len(sys.argv) not in (5, 6) or sys.argv[1] != GUARD:
        sys.exit(
            "usage: python -m mapservice.local.lifetime guard PID_FILE PARENT_PID MARK [SETTLE_S]"
        )
    guard(
        Path(sys.argv[2]),
        int(sys.argv[3]),
        sys.argv[4],
        float(sys.argv[5]) if len(sys.argv) == 6 else SETTLE_S,
    )
