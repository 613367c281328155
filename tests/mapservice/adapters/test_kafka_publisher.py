"""The Kafka publisher does no I/O until the first publish (no broker needed here)."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator

import psutil
import pytest

from mapservice.adapters.kafka_publisher import KafkaPublisher, producer_config
from mapservice.local.embedded import free_port
from mapservice.settings import Settings

UNREACHABLE = Settings(kafka_bootstrap="127.0.0.1:9")


def test_constructing_poll_and_flush_create_no_producer() -> None:
    """A publisher that never published has no librdkafka producer dialling the broker."""
    pub = KafkaPublisher(UNREACHABLE, client_id="idle-api")
    pub.poll(0.0)
    assert pub.flush(0.1) == 0
    assert not pub.connected


@pytest.fixture
def poster() -> Iterator[KafkaPublisher]:
    pub = KafkaPublisher(UNREACHABLE, client_id="poster")
    yield pub
    pub.close()


def test_first_publish_creates_the_producer_and_queues_the_message(poster) -> None:
    """The first publish makes the producer; the undelivered message stays queued until
    close() purges it and closes the producer."""
    poster.publish("t", b"k", b"v", lambda error: None)
    assert poster.connected and poster.flush(0.1) == 1
    assert poster.close() == 1 and not poster.connected


def test_producer_config_keeps_keys_on_faust_partitions() -> None:
    """Idempotent, acks=all, and murmur2_random partitioning as aiokafka/faust use."""
    config = producer_config(UNREACHABLE, "c")
    assert (config["enable.idempotence"], config["acks"], config["partitioner"]) == (
        True,
        "all",
        "murmur2_random",
    )


def test_producer_linger_comes_from_the_kafka_linger_setting() -> None:
    """MAPSERVICE_KAFKA_LINGER_MS sets librdkafka's linger.ms (50 ms unless set)."""
    assert producer_config(UNREACHABLE, "c")["linger.ms"] == 50
    tuned = Settings(kafka_bootstrap="127.0.0.1:9", kafka_linger_ms=5)
    assert producer_config(tuned, "c")["linger.ms"] == 5


# A process publishing through a broker that is gone, as the gateway's loop does: each
# record times out (here after 200 ms, not 10 s), the producer is renewed (here at once, not
# at most every 10 s; librdkafka looks for timed-out records once a second), the record is
# produced again; once it went through `argv[2]` renewals (or after a minute, whichever is
# first: the test then says how few there were) it prints how many renewals it went through
# and its thread count, and stays idle. The
# cyclic collector off, as good as in a gateway that allocates little (frozen heap, high
# thresholds: runtime/heap.py).
OUTAGE = """
import gc, os, sys, time
from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.settings import Settings
gc.disable()
pub = KafkaPublisher(Settings(kafka_bootstrap=sys.argv[1]), "outage", renew_interval_s=0,
                     message_timeout_ms=200)
failed = []
pub.publish("t", b"k", b"v", failed.append)
timeouts = 0
deadline = time.monotonic() + 60
while timeouts < int(sys.argv[2]) and time.monotonic() < deadline:
    pub.poll(0.05)
    if failed:
        timeouts += len(failed)
        failed.clear()
        pub.publish("t", b"k", b"v", failed.append)
while pub._retiring:  # the last renewal's producer served
    pub.poll(0.05)
print("RESULT", timeouts, len(os.listdir("/proc/self/task")), file=sys.stderr, flush=True)
time.sleep(60)
"""


def cpu_share(process: psutil.Process, seconds: float) -> float:
    """The share of one core `process` used over `seconds` (user and system)."""
    before, started = process.cpu_times(), time.monotonic()
    time.sleep(seconds)
    after = process.cpu_times()
    used = (after.user - before.user) + (after.system - before.system)
    return used / (time.monotonic() - started)


def test_a_publisher_whose_broker_is_gone_stays_idle_however_often_it_was_renewed() -> None:
    """Through an outage the producer is renewed again and again: each renewed producer is
    released, so none of them goes on dialling the gone broker. (Before, each lived on,
    three threads apiece, dialling: about 0.2 % of a core each, 41 % in a gateway whose
    brokers had been gone half an hour.)"""
    outage = subprocess.Popen(
        [sys.executable, "-c", OUTAGE, f"127.0.0.1:{free_port()}", "10"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,  # librdkafka's log lines, then the result
        text=True,
    )
    try:
        assert outage.stderr is not None
        result = next(line for line in outage.stderr if line.startswith("RESULT "))
        timeouts, threads = (int(n) for n in result.split()[1:])
        assert timeouts >= 10, f"only {timeouts} renewals: the outage was not simulated"
        time.sleep(1)  # what was being released is
        share = cpu_share(psutil.Process(outage.pid), 4)
        print(f"\n{timeouts} renewals: {threads} threads, {share:.1%} of a core idle")
        assert threads < 10, f"{threads} threads after {timeouts} renewals: producers kept"
        assert share < 0.05, f"{share:.1%} of a core with its broker gone"
    finally:
        outage.kill()
        outage.wait()
