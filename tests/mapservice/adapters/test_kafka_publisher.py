"""The Kafka publisher does no I/O until the first publish (no broker needed here)."""

from __future__ import annotations

from mapservice.adapters.kafka_publisher import KafkaPublisher, producer_config
from mapservice.settings import Settings

UNREACHABLE = Settings(kafka_bootstrap="127.0.0.1:9")


def test_constructing_poll_and_flush_create_no_producer() -> None:
    """A publisher that never published has no librdkafka producer dialling the broker."""
    pub = KafkaPublisher(UNREACHABLE, client_id="idle-api")
    pub.poll(0.0)
    assert pub.flush(0.1) == 0
    assert not pub.connected


def test_first_publish_creates_the_producer_and_queues_the_message() -> None:
    """The first publish makes the producer; the undelivered message stays queued."""
    pub = KafkaPublisher(UNREACHABLE, client_id="poster")
    pub.publish("t", b"k", b"v", lambda error: None)
    assert pub.connected and pub.flush(0.1) == 1
    # Purged and served, the undelivered message lets go of its producer, which would
    # otherwise dial the unreachable broker for the rest of the test run.
    pub._producer.purge()
    assert pub.flush(0.1) == 0


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
