"""Embedded ClickHouse's merges at a lower CPU priority than the ingest path.

With chDB, ClickHouse merges the history's parts in this process, on threads it names
`MergeMutate`, and on a small machine those merges compete for a core with the inserts
that make events queryable. Their cost grows as the day's parts grow: at 1,000 VDA 5050
vehicles they took 15 % of a core in the first minute and 37 % in the eleventh, and the
inserts, waiting for a core behind them, took twice as long (BENCHMARKS.md, "Merges").

Linux keeps a nice value per thread, so those threads alone get a higher one: they still
use every idle cycle, but give way to the threads that insert, consume and serve. A
ClickHouse server does the same for its own merges with its server setting
`os_threads_nice_value_merge_mutate`.

ClickHouse starts merge threads when it needs them, so the priorities are applied again
every few seconds rather than once.
"""

from __future__ import annotations

import asyncio
import os
import sys
from pathlib import Path

import structlog

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


async def keep_merges_low(
    nice: int, every_s: float = EVERY_S, names: frozenset[str] = MERGE_THREADS
) -> None:
    """Applies `lower_priority(nice, names)` now and every `every_s` until cancelled (off the
    event loop: reading a few hundred threads' names takes milliseconds)."""
    loop = asyncio.get_running_loop()
    total = 0
    while True:
        changed = await loop.run_in_executor(None, lower_priority, nice, names)
        if changed:
            total += changed
            log.info("chDB merge threads at a lower CPU priority", nice=nice, threads=total)
        await asyncio.sleep(every_s)
