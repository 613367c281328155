"""CPU time and resident memory of a component process and its children, as the
benchmarks (ingest, soak) read them from /proc through psutil."""

from __future__ import annotations

import psutil


def cpu_seconds(proc: psutil.Process) -> float:
    """CPU time of a process, its reaped children and its live ones (user + system); 0 when
    it is gone."""
    total = 0.0
    try:
        t = proc.cpu_times()
        total += t.user + t.system + t.children_user + t.children_system
        for child in proc.children(recursive=True):
            try:
                c = child.cpu_times()
                total += c.user + c.system
            except psutil.Error:
                pass
    except psutil.Error:
        pass
    return total


def resident_mb(proc: psutil.Process) -> tuple[float, float]:
    """Resident MB of the process and its children: all, and anonymous only (resident minus
    file-backed and shared pages: heap, stacks, arenas)."""
    total = anon = 0
    for p in [proc, *_children(proc)]:
        try:
            info = p.memory_info()
            total += info.rss
            anon += info.rss - info.shared
        except psutil.Error:
            pass
    return total / 1e6, anon / 1e6


def resident_by_component(procs: dict) -> dict[str, float]:
    """Resident MB of each component process (with its children), by component name."""
    return {
        name: round(resident_mb(psutil.Process(proc.pid))[0], 1)
        for name, proc in procs.items()
        if proc.poll() is None
    }


def _children(proc: psutil.Process) -> list[psutil.Process]:
    try:
        return proc.children(recursive=True)
    except psutil.Error:
        return []
