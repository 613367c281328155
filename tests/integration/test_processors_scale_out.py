"""Scale-out of the processors, as Kubernetes runs them: two `mapservice processors`
replicas on a topic of one partition, against one ClickHouse server (`mapservice
clickhouse-server`). The replica without partitions is a healthy standby; the snapshot
timer runs on one replica only, and on the other once the first is killed.

Bounded: each wait is at most 90 s; about half a minute on an idle machine."""

from __future__ import annotations

import re
import signal
import time

import httpx
import pytest

from mapservice.local import embedded
from mapservice.local.stack import Stack

REPLICAS = ("processors-1", "processors-2")


def snapshot_runs(port: int) -> float:
    text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
    found = re.search(r"^mapservice_snapshot_runs_total ([0-9.e+]+)$", text, re.M)
    return float(found.group(1)) if found else 0.0


def healthy(port: int) -> bool:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = Stack(
        tmp_path_factory.mktemp("scale-out"),
        mqtt="mosquitto",
        apart=True,
        extra_env={
            "MAPSERVICE_KAFKA_PARTITIONS": "1",  # one replica gets it, the other none
            "MAPSERVICE_SNAPSHOT_EVERY_S": "4",  # the timer ticks every second
            # The killed replica's partition goes to the standby 3 s after it died, not 10.
            "MAPSERVICE_KAFKA_SESSION_TIMEOUT_S": "3",
        },
    )
    stack.ports = [embedded.free_port() for _ in REPLICAS]  # type: ignore[attr-defined]
    with stack.running(
        stack.start_brokers,
        stack.start_clickhouse_server,
        *(
            lambda p=port, n=name: stack.start_processors(p, n)
            for port, name in zip(stack.ports, REPLICAS)
        ),
    ):
        yield stack


def test_a_replica_without_partitions_is_a_healthy_standby(stack) -> None:
    """Both replicas answer /healthz 200 although only one owns the partition."""
    deadline = time.monotonic() + 90
    while not all(healthy(p) for p in stack.ports):
        assert time.monotonic() < deadline, "a replica never became healthy"
        time.sleep(1)


def test_the_snapshot_timer_runs_on_one_replica_and_moves_when_it_dies(stack) -> None:
    """Over five ticks of the timer exactly one replica runs it; after SIGKILL of that one
    the other does."""
    deadline = time.monotonic() + 60
    while max(runs := [snapshot_runs(p) for p in stack.ports]) < 5:
        assert time.monotonic() < deadline, f"the timer did not tick five times: {runs}"
        time.sleep(0.2)
    assert sorted(r > 0 for r in runs) == [False, True], runs
    leader = runs.index(max(runs))
    name = REPLICAS[leader]
    stack.procs[name].send_signal(signal.SIGKILL)
    stack.procs[name].wait(10)
    other = stack.ports[1 - leader]
    before = snapshot_runs(other)
    deadline = time.monotonic() + 90
    while snapshot_runs(other) <= before + 2:
        assert time.monotonic() < deadline, "the standby never took the timer over"
        time.sleep(0.2)
    assert healthy(other)
