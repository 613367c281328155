"""The fast tests' check for librdkafka clients left open (`_kafka_clients_closed` in
tests/conftest.py) counts the clients a test made, not the threads older clients start."""

from __future__ import annotations

import time
from pathlib import Path

from confluent_kafka import Producer

from tests.conftest import librdkafka_clients, thread_ids

SETTLE_S = 0.05  # see librdkafka_clients
UNREACHABLE = {
    "bootstrap.servers": "127.0.0.1:1",
    "log_level": 0,
    "reconnect.backoff.ms": 10,
    "reconnect.backoff.max.ms": 50,
}


def broker_threads() -> set[str]:
    ids = set()
    for task in Path("/proc/self/task").iterdir():
        try:
            if (task / "comm").read_text().startswith("rdk:broker"):
                ids.add(task.name)
        except OSError:
            continue
    return ids


def test_an_older_client_bootstrapping_again_is_not_a_new_client() -> None:
    """A client whose brokers are gone bootstraps again (librdkafka >= 2.10) with new broker
    threads, at any moment: counting threads blamed that on the fast test running then."""
    old = Producer({**UNREACHABLE, "metadata.recovery.rebootstrap.trigger.ms": 100})
    try:
        old.produce("t", b"x")  # something to deliver: it keeps asking for the brokers
        clients, first = librdkafka_clients(SETTLE_S), broker_threads()
        started: set[str] = set()
        ended: set[str] = set()
        deadline = time.monotonic() + 60
        # A broker thread of a bootstrap may live only briefly on a busy machine, so the
        # threads are read often, and a first broker thread ending counts as a bootstrap too.
        while not started and time.monotonic() < deadline:
            old.poll(0)
            now = broker_threads()
            started |= now - first
            if first - now and not ended:  # decommissioned: its successor is due shortly
                deadline = min(deadline, time.monotonic() + 5)
            ended |= first - now
            if librdkafka_clients() - clients:  # a thread just made reads rdk:main briefly
                assert not librdkafka_clients(SETTLE_S) - clients, "counted as a new client"
            time.sleep(0.005)
        assert started or ended, "the old client did not bootstrap again within 60 s"
        assert not librdkafka_clients(SETTLE_S) - clients
    finally:
        close(old)


def test_a_client_left_open_is_counted() -> None:
    before = librdkafka_clients(SETTLE_S)
    left_open = Producer(UNREACHABLE)
    try:
        assert len(librdkafka_clients(SETTLE_S) - before) == 1
    finally:
        close(left_open)
    assert not librdkafka_clients(SETTLE_S) - before


def test_a_client_left_open_is_among_the_threads_new_since_the_test_began() -> None:
    """The per-test check reads only the threads made since the test began: a client made
    then is among them."""
    before = thread_ids()
    left_open = Producer(UNREACHABLE)
    try:
        new = thread_ids() - before
        assert len(librdkafka_clients(SETTLE_S, among=new)) == 1
    finally:
        close(left_open)
    assert not librdkafka_clients(SETTLE_S, among=thread_ids() - before)


def close(producer: Producer) -> None:
    producer.purge()
    producer.flush(0)
    producer.close()
