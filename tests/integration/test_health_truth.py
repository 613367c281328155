"""Health that tells the truth, tested by killing each dependency of the split deployment
(gateway, processors and API as separate processes; Mosquitto, Apache Kafka and the
ClickHouse HTTP interface over chDB): the components stay alive (/healthz 200) but say they
are not ready (/readyz 503, naming the dependency) while it is gone, and ready again once it
is back. Kafka comes last: the embedded Apache Kafka restarts on its log.

Bounded: each wait is at most 60 s; about two minutes on an idle machine."""

from __future__ import annotations

import signal
import time

import httpx
import pytest

from mapservice.local.stack import Stack


def get(url: str) -> tuple[int, dict]:
    try:
        reply = httpx.get(url, timeout=10)
        return reply.status_code, reply.json()
    except httpx.HTTPError as exc:
        return 0, {"error": str(exc)}


def until(what: str, predicate, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for: {what}"
        time.sleep(0.5)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = Stack(
        tmp_path_factory.mktemp("health"),
        mqtt="mosquitto",
        apart=True,
        extra_env={
            # /readyz asks Kafka every second, not every 5 s: a change shows within 1 s.
            "MAPSERVICE_KAFKA_CHECK_TTL_S": "1",
        },
    )
    with stack.running(stack.start_brokers, stack.start_apart, stack.start_gateway):
        yield stack


def urls(stack) -> dict[str, str]:
    return {
        "gateway": f"http://127.0.0.1:{stack.health_port}",
        "processors": f"http://127.0.0.1:{stack.processors_health_port}",
        "api": stack.api_url,
    }


def all_ready(stack) -> bool:
    return all(get(f"{u}/readyz")[0] == 200 for u in urls(stack).values())


def all_alive(stack) -> bool:
    return all(get(f"{u}/healthz")[0] == 200 for u in urls(stack).values())


def kill(stack, name: str) -> None:
    proc = stack.procs.pop(name)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)


def test_everything_is_ready_with_every_dependency_up(stack) -> None:
    """The starting point: every component alive and ready."""
    until("all ready", lambda: all_ready(stack))
    assert all_alive(stack)


def test_without_the_mqtt_broker_the_gateway_is_alive_but_not_ready(stack) -> None:
    """Mosquitto killed: the gateway's /readyz says mqtt_connected false; back when it is."""
    gateway = urls(stack)["gateway"]
    kill(stack, "mqtt")
    until(
        "gateway unready",
        lambda: (
            get(f"{gateway}/readyz") == (503, get(f"{gateway}/readyz")[1])
            and get(f"{gateway}/readyz")[1].get("mqtt_connected") is False
        ),
    )
    assert get(f"{gateway}/healthz")[0] == 200
    stack.start_mqtt()
    until("gateway ready again", lambda: get(f"{gateway}/readyz")[0] == 200)


def test_without_clickhouse_processors_and_api_are_not_ready(stack) -> None:
    """The ClickHouse server killed: processors and API /readyz 503 with clickhouse false,
    both still alive; ready again once it is back."""
    kill(stack, "clickhouse")
    for name in ("processors", "api"):
        url = urls(stack)[name]
        until(
            f"{name} unready",
            lambda url=url: (
                get(f"{url}/readyz")[0] == 503
                and get(f"{url}/readyz")[1]["checks"]["clickhouse"] is False
            ),
        )
        assert get(f"{url}/healthz")[0] == 200, name
    stack.start_clickhouse_server()
    until("all ready again", lambda: all_ready(stack))


def test_without_kafka_the_writers_are_not_ready_and_the_api_says_so(stack) -> None:
    """Kafka killed: gateway and processors /readyz 503 (kafka false); the API stays ready
    for reads and reports kafka false; all stay alive, and are ready again once Kafka is
    back on its log."""
    kill(stack, "kafka")
    for name in ("gateway", "processors"):
        url = urls(stack)[name]
        until(f"{name} unready", lambda url=url: get(f"{url}/readyz")[0] == 503)
        body = get(f"{url}/readyz")[1]
        assert body.get("kafka", body.get("checks", {}).get("kafka")) is False, body
    api = urls(stack)["api"]
    until("api reports kafka down", lambda: get(f"{api}/readyz")[1]["checks"].get("kafka") is False)
    assert get(f"{api}/readyz")[0] == 200
    assert all_alive(stack)
    stack.start_kafka()
    until("all ready again", lambda: all_ready(stack), timeout_s=90)
