"""KafkaLivePublisher: best effort, never blocks or raises into the history sink."""

from __future__ import annotations

import time

from prometheus_client import REGISTRY

from mapservice.adapters.kafka_live_publisher import KafkaLivePublisher, live_producer_config
from mapservice.settings import Settings


def dropped() -> float:
    return REGISTRY.get_sample_value("mapservice_live_records_dropped_total") or 0.0


class FullProducer:
    """A librdkafka producer whose local queue is full."""

    polled = 0

    def produce(self, *args, **kwargs) -> None:
        raise BufferError("Local: Queue full")

    def poll(self, timeout: float) -> int:
        self.polled += 1
        return 0


def test_a_full_local_queue_drops_and_counts_instead_of_blocking(ev) -> None:
    """publish() returns at once when the producer's queue is full; the record is counted as dropped."""
    publisher = KafkaLivePublisher(Settings(kafka_bootstrap="127.0.0.1:1"))
    publisher._producer = FullProducer()
    before = dropped()
    publisher.publish([ev.pose("r1", 1_000), ev.chunk("r1", 1_000)])
    assert dropped() == before + 1  # one record for the batch
    assert publisher._producer.polled == 1


def test_an_undelivered_record_is_counted() -> None:
    """A delivery error (e.g. not delivered within message.timeout.ms) counts as dropped."""
    before = dropped()
    KafkaLivePublisher._delivered("timed out", None)
    KafkaLivePublisher._delivered(None, None)
    assert dropped() == before + 1


def test_live_records_give_up_after_seconds_and_batch_briefly() -> None:
    """A live record older than 5 s is worthless: short delivery timeout, 5 ms linger."""
    conf = live_producer_config(Settings(), "p")
    assert conf["message.timeout.ms"] == 5_000 and conf["linger.ms"] == 5


def test_close_drops_what_was_not_delivered_and_ends_the_client(ev) -> None:
    """On an unreachable broker close() waits its timeout, counts the records it drops, and
    ends the client (no librdkafka thread goes on dialling)."""
    from tests.conftest import librdkafka_clients

    before_clients, before = librdkafka_clients(), dropped()
    publisher = KafkaLivePublisher(Settings(kafka_bootstrap="127.0.0.1:1"))
    publisher.publish([ev.pose("r1", 1_000), ev.pose("r2", 1_000)])
    assert librdkafka_clients() - before_clients
    started = time.monotonic()
    publisher.close(timeout_s=0.2)
    assert time.monotonic() - started < 5
    assert dropped() == before + 1  # the batch's one record
    assert not librdkafka_clients(settle_s=0.05) - before_clients
    publisher.close()  # twice is harmless
