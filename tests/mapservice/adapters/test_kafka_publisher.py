"""The Kafka publisher does no I/O until the first publish (no broker needed here)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from mapservice.adapters.kafka_publisher import KafkaPublisher, producer_config
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
