"""The benchmarks' process readings: CPU counts reaped children, memory splits anonymous."""

from __future__ import annotations

import subprocess
import sys

import psutil

from mapservice.bench.procstat import cpu_seconds, resident_mb


def test_cpu_seconds_include_a_child_that_has_exited() -> None:
    """A component's CPU time keeps what its finished children used."""
    me = psutil.Process()
    before = cpu_seconds(me) - sum(me.cpu_times()[:2])
    subprocess.run([sys.executable, "-c", "sum(range(20_000_000))"], check=True)
    after = cpu_seconds(me) - sum(me.cpu_times()[:2])
    assert after - before > 0.05


def test_resident_memory_is_split_into_all_and_anonymous() -> None:
    """Anonymous memory is a positive part of the resident total."""
    total, anon = resident_mb(psutil.Process())
    assert 0 < anon <= total


def test_a_process_that_is_gone_reads_as_nothing() -> None:
    """A component that exited reads 0 s and 0 MB rather than raising."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    gone = psutil.Process(proc.pid)
    proc.wait()
    assert cpu_seconds(gone) == 0.0 and resident_mb(gone) == (0.0, 0.0)
