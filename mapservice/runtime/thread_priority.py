"""Embedded ClickHouse's merges at a lower CPU priority than the ingest path.

With chDB, ClickHouse merges the history's parts inside the process that holds the chDB
directory (`serve`, or `mapservice clickhouse-server` in `make up`), on threads it names
`MergeMutate`, and on a small machine those merges compete for a core with the inserts
that make events queryable. Their cost grows as the day's parts grow: at 1,000 VDA 5050
vehicles they took 15 % of a core in the first minute and 37 % in the eleventh, and the
inserts, waiting for a core behind them, took twice as long (BENCHMARKS.md, "Merges").

Linux keeps a nice value per thread, so those threads alone get a higher one: they still
use every idle cycle, but give way to the threads that insert, consume and serve. Raising
a thread's nice value needs no privilege; ClickHouse's own server setting for this,
`os_threads_nice_value_merge_mutate`, needs CAP_SYS_NICE and is not set in chDB.

ClickHouse starts merge threads when it needs them, so the priorities are applied again
every few seconds rather than once.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import structlog

from mapservice.settings import Settings

log = structlog.get_logger(__name__)

MERGE_THREADS = frozenset({"MergeMutate"})
TASKS = Path("/proc/self/task")
EVERY_S = 5.0


def supported() -> bool:
    """Per-thread nice values (and /proc to name the threads) are Linux's."""
    return sys.platform.startswith("linux") and TASKS.is_dir()


def thread_names(tasks: Path = TASKS) -> dict[int, str]:
    """Each thread of this process (its id) and its name; a thread that ends meanwhile is
    left out."""
    names: dict[int, str] = {}
    for task in tasks.iterdir():
        try:
            names[int(task.name)] = (task / "comm").read_text().strip()
        except (OSError, ValueError):
            continue
    return names


def lower_priority(nice: int, names: frozenset[str] = MERGE_THREADS, tasks: Path = TASKS) -> int:
    """Sets every thread called one of `names` whose nice value is below `nice` to `nice`;
    returns how many it changed. Raising a thread's own nice value needs no privilege."""
    changed = 0
    for tid, name in thread_names(tasks).items():
        if name not in names:
            continue
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) < nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
                changed += 1
        except (ProcessLookupError, PermissionError):
            continue  # ended meanwhile; or a thread of another user's, which cannot be
    return changed


class MergePriorityKeeper:
    """Applies `lower_priority(nice, names)` at once and every `every_s` on a daemon thread
    of its own (a process that only serves HTTP, like `mapservice clickhouse-server`, has
    no loop of ours to run it on), until stopped or the process ends."""

    def __init__(
        self, nice: int, every_s: float = EVERY_S, names: frozenset[str] = MERGE_THREADS
    ) -> None:
        self.nice, self.every_s, self.names = nice, every_s, names
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="merge-priority", daemon=True)

    def start(self) -> MergePriorityKeeper:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        total = 0
        while not self._stop.is_set():
            try:
                changed = lower_priority(self.nice, self.names)
            except OSError as exc:  # /proc unreadable: say so once, leave the priorities
                log.warning("cannot set the merge threads' CPU priority", error=str(exc))
                return
            if changed:
                total += changed
                log.info(
                    "chDB merge threads at a lower CPU priority", nice=self.nice, threads=total
                )
            self._stop.wait(self.every_s)


def keep_merges_low(settings: Settings) -> MergePriorityKeeper | None:
    """Starts the keeper for this process's embedded chDB, as `MAPSERVICE_CHDB_MERGE_NICE`
    asks (0: none); None where it is off or not supported."""
    if not settings.chdb_merge_nice or not supported():
        return None
    return MergePriorityKeeper(settings.chdb_merge_nice).start()
