"""Merge threads at a lower CPU priority: named threads of this process, and chDB's own."""

from __future__ import annotations

import ctypes
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from mapservice.runtime.thread_priority import (
    MERGE_THREADS,
    MergePriorityKeeper,
    keep_merges_low,
    lower_priority,
    supported,
    thread_names,
)
from mapservice.settings import Settings

pytestmark = pytest.mark.skipif(not supported(), reason="per-thread nice values are Linux's")

PR_SET_NAME = 15


def nice_of(tid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


@contextmanager
def named_thread(name: str) -> Iterator[int]:
    """A thread of this process that names itself `name` (as ClickHouse's do) and waits;
    yields its id."""
    ready, done = threading.Event(), threading.Event()
    tid: list[int] = []

    def run() -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_NAME, name.encode(), 0, 0, 0)
        tid.append(threading.get_native_id())
        ready.set()
        done.wait()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    ready.wait(5)
    try:
        yield tid[0]
    finally:
        done.set()
        thread.join(5)


def test_only_the_named_threads_get_the_higher_nice_value() -> None:
    with named_thread("ms-merge") as merge, named_thread("ms-insert") as insert:
        assert thread_names()[merge] == "ms-merge"
        before = nice_of(insert)
        assert lower_priority(7, frozenset({"ms-merge"})) == 1
        assert nice_of(merge) == 7
        assert nice_of(insert) == before
        assert nice_of(threading.get_native_id()) == before
        # Applied again, nothing left to change.
        assert lower_priority(7, frozenset({"ms-merge"})) == 0


def test_a_thread_already_lower_is_left_as_it_is() -> None:
    with named_thread("ms-merge") as merge:
        os.setpriority(os.PRIO_PROCESS, merge, 12)
        assert lower_priority(7, frozenset({"ms-merge"})) == 0
        assert nice_of(merge) == 12


def test_the_keeper_applies_it_at_once_and_again_to_later_threads() -> None:
    with named_thread("ms-merge") as first:
        keeper = MergePriorityKeeper(5, every_s=0.05, names=frozenset({"ms-merge"})).start()
        try:
            wait_for(lambda: nice_of(first) == 5)
            with named_thread("ms-merge") as later:
                wait_for(lambda: nice_of(later) == 5)
        finally:
            keeper.stop()


def test_the_setting_turns_the_keeper_off() -> None:
    # On, it is started by `serve` and `clickhouse-server` (tests/integration).
    assert keep_merges_low(Settings(chdb_merge_nice=0)) is None


def wait_for(condition, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "not applied in time"
        time.sleep(0.02)


def test_chdb_merges_run_on_threads_of_the_expected_name(chdb_dir) -> None:
    """The name this module looks for is what embedded chDB calls its merge threads: a
    table that needs merging gets its merges on threads named in MERGE_THREADS."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore

    store = ClickHouseStore(f"chdb://{chdb_dir}", database="merges")
    try:
        client = store.client
        client.command("CREATE DATABASE IF NOT EXISTS merges")
        client.command("CREATE TABLE merges.t (x UInt64) ENGINE = MergeTree ORDER BY x")
        for n in range(12):
            client.command(f"INSERT INTO merges.t SELECT number + {n * 1000} FROM numbers(1000)")
        deadline = time.monotonic() + 60
        while not MERGE_THREADS & set(thread_names().values()):
            assert time.monotonic() < deadline, (
                f"no thread named {sorted(MERGE_THREADS)} after parts to merge: chDB's merge "
                f"threads are now called something else ({sorted(set(thread_names().values()))})"
            )
            time.sleep(0.1)
        merges = [t for t, name in thread_names().items() if name in MERGE_THREADS]
        previous = {t: nice_of(t) for t in merges}
        try:
            lower_priority(19)
            assert all(nice_of(t) == 19 for t in merges)
        finally:
            for t, nice in previous.items():
                try:
                    os.setpriority(os.PRIO_PROCESS, t, nice)  # root may; others keep 19
                except (PermissionError, ProcessLookupError):
                    pass
    finally:
        store.close()
