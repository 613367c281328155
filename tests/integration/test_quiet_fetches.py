"""A quiet plant costs the broker little: the history's and the live relay's consumers, on
the default settings against Apache Kafka (the session's shared node), send a few fetches
a second while no record comes, and a record that comes is still read at once (the broker
answers a waiting fetch on arrival, so the longer wait costs no latency).

Bounded: a few seconds per consumer."""

from __future__ import annotations

import json
import time
import uuid

import pytest
from confluent_kafka import Consumer, Producer
from confluent_kafka.admin import AdminClient, NewTopic

from mapservice.adapters.kafka_batch_source import consumer_config
from mapservice.adapters.kafka_live_relay import live_consumer_config
from mapservice.settings import Settings

QUIET_S = 4.0


def fetches_sent(stats: list[dict]) -> int:
    """Fetch requests the client sent to the brokers (librdkafka's statistics)."""
    last = stats[-1]
    return sum(
        broker.get("req", {}).get("Fetch", 0)
        for name, broker in last["brokers"].items()
        if not name.startswith("GroupCoordinator")
    )


@pytest.mark.parametrize("role", ["history", "live relay"])
def test_a_quiet_consumer_fetches_a_few_times_a_second_and_reads_a_record_at_once(
    apache_kafka, role
) -> None:
    topic = f"test-quiet-{uuid.uuid4().hex[:8]}"
    admin = AdminClient({"bootstrap.servers": apache_kafka})
    admin.create_topics([NewTopic(topic, 1, 1)])[topic].result(timeout=30)
    settings = Settings(kafka_bootstrap=apache_kafka)
    config = (
        consumer_config(settings, f"quiet-{uuid.uuid4().hex[:8]}")
        if role == "history"
        else live_consumer_config(settings)
    )
    stats: list[dict] = []
    consumer = Consumer(
        {
            **config,
            "auto.offset.reset": "latest",
            "statistics.interval.ms": 500,
            "stats_cb": lambda s: stats.append(json.loads(s)),
        }
    )
    producer = Producer({"bootstrap.servers": apache_kafka})
    try:
        consumer.subscribe([topic])
        deadline = time.monotonic() + 30
        while not consumer.assignment():  # joined, fetching from the end
            assert time.monotonic() < deadline, "no partition assigned"
            consumer.poll(0.2)
        consumer.poll(1.0)
        before, quiet_from = fetches_sent(stats), time.monotonic()
        while time.monotonic() - quiet_from < QUIET_S:
            assert consumer.poll(0.2) is None
        per_s = (fetches_sent(stats) - before) / (time.monotonic() - quiet_from)
        # 2 a second at the 500 ms wait, plus the statistics' own lag; 20 at 50 ms.
        assert per_s <= 4, f"{per_s:.1f} fetches a second while no record came"

        sent = time.monotonic()
        producer.produce(topic, b"a record")
        producer.flush(10)
        while (message := consumer.poll(0.05)) is None:
            assert time.monotonic() - sent < 10, "the record was not read"
        assert message.value() == b"a record"
        # Answered on arrival: well inside the 500 ms the fetch may wait.
        assert time.monotonic() - sent < 0.4
    finally:
        consumer.close()
