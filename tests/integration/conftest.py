"""Real brokers and embedded ClickHouse: each module gets its own running stack."""

from __future__ import annotations

import time

import httpx
import pytest
from confluent_kafka import OFFSET_BEGINNING, Consumer, TopicPartition

from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.local.stack import Stack
from tests.fixtures.paths import MAPS


def pytest_collection_modifyitems(items):
    for item in items:
        if "/integration/" in str(item.fspath):
            item.add_marker(pytest.mark.integration)


def start_stack(
    tmp_path_factory, mqtt: str, extra_env: dict[str, str] | None = None, gateways: int = 1
) -> Stack:
    stack = Stack(
        tmp_path_factory.mktemp(f"stack-{mqtt}"),
        mqtt=mqtt,
        extra_env=extra_env or {},
        gateways=gateways,
    )
    return run_stack(stack, meta_for(load_ros_map(MAPS / "depot.yaml")))


def run_stack(stack: Stack, meta) -> Stack:
    """Brokers, the map meta, processors + API and gateway, ready to validate; all stopped
    again if any part fails to start."""
    stack.start(
        stack.start_brokers,
        lambda: stack.publish_meta(meta),
        stack.start_server,
        stack.start_gateways,
        lambda: wait_for_meta(stack),
    )
    return stack


def wait_for_meta(stack: Stack, timeout_s: float = 30) -> None:
    """The gateway validates against the map meta once its watcher has read it."""
    log = stack.log_dir / "gateway.log"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if log.exists() and "map meta applied" in log.read_text():
            return
        time.sleep(0.1)
    raise AssertionError("gateway never applied the map meta")


@pytest.fixture(scope="module")
def mosquitto_stack(tmp_path_factory):
    stack = start_stack(tmp_path_factory, "mosquitto")
    yield stack
    stack.stop()


@pytest.fixture(scope="module")
def amqtt_stack(tmp_path_factory):
    stack = start_stack(tmp_path_factory, "amqtt")
    yield stack
    stack.stop()


def stored_keys(stack: Stack, kind: str, robot_prefix: str, from_ms: int, to_ms: int) -> list:
    path = "/api/v1/poses" if kind == "pose" else "/api/v1/chunk-events"
    rows = httpx.get(
        f"{stack.api_url}{path}", params={"from": from_ms, "to": to_ms, "limit": 100000}, timeout=30
    ).json()
    return [(r["robotId"], r["ts_ms"]) for r in rows if r["robotId"].startswith(robot_prefix)]


def wait_for_count(
    stack: Stack,
    kind: str,
    robot_prefix: str,
    from_ms: int,
    to_ms: int,
    expected: int,
    timeout_s: float = 60,
) -> list:
    deadline = time.monotonic() + timeout_s
    keys: list = []
    while time.monotonic() < deadline:
        keys = stored_keys(stack, kind, robot_prefix, from_ms, to_ms)
        if len(keys) >= expected:
            time.sleep(1.0)  # anything extra (a duplicate) would show up now
            return stored_keys(stack, kind, robot_prefix, from_ms, to_ms)
        time.sleep(0.25)
    return keys


def read_topic(stack: Stack, topic: str, min_records: int, timeout_s: float = 30) -> list[bytes]:
    settings = stack.settings()
    consumer = Consumer(
        {**settings.kafka_config(), "group.id": "test-reader", "enable.auto.commit": False}
    )
    try:
        md = consumer.list_topics(topic, timeout=10)
        consumer.assign(
            [TopicPartition(topic, p, OFFSET_BEGINNING) for p in md.topics[topic].partitions]
        )
        values: list[bytes] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and len(values) < min_records:
            msg = consumer.poll(0.5)
            if msg is not None and not msg.error():
                values.append(msg.value())
        # Drain whatever else is there.
        while (msg := consumer.poll(1.0)) is not None:
            if not msg.error():
                values.append(msg.value())
        return values
    finally:
        consumer.close()


def merge_threads_lowered(pid: int, make_parts, nice: int = 19, timeout_s: float = 90) -> list:
    """Calls `make_parts(round)` until process `pid` has merge threads, all at `nice` (the
    default MAPSERVICE_CHDB_MERGE_NICE); returns their ids. Its other threads, the inserts'
    among them, must not have taken that value."""
    import os
    from pathlib import Path

    from mapservice.runtime.thread_priority import MERGE_THREADS, thread_names

    tasks = Path(f"/proc/{pid}/task")
    deadline = time.monotonic() + timeout_s
    merges: list[int] = []
    round_ = 0
    while time.monotonic() < deadline:
        make_parts(round_)
        round_ += 1
        time.sleep(0.3)  # a batch each: one part per table, until parts get merged
        merges = [t for t, name in thread_names(tasks).items() if name in MERGE_THREADS]
        if merges and all(os.getpriority(os.PRIO_PROCESS, t) == nice for t in merges):
            break
    names = thread_names(tasks)
    assert merges, f"no merge thread in process {pid}: {sorted(set(names.values()))}"
    assert all(os.getpriority(os.PRIO_PROCESS, t) == nice for t in merges)
    assert os.getpriority(os.PRIO_PROCESS, pid) < nice
    others = [t for t, name in names.items() if name not in MERGE_THREADS]
    assert not [t for t in others if os.getpriority(os.PRIO_PROCESS, t) == nice]
    return merges
