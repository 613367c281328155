"""One contract for every EventPublisher: the memory twin (mapservice/testing/
memory_publisher.py) and KafkaPublisher on Apache Kafka (the session's embedded node; those
cases are integration tests): a record is in the log once its `on_done(None)` has run,
callbacks run inside `poll`/`flush` (the caller's thread), once per record, and a log that
cannot take a record says so through `on_done(error)`."""

from __future__ import annotations

import gc
import time
import uuid
from collections.abc import Iterator

import pytest

from mapservice.core.ports import EventPublisher
from mapservice.testing.memory_publisher import MemoryPublisher


class MemoryKit:
    def __init__(self) -> None:
        self.topic = "contract-records"
        self.made: list[MemoryPublisher] = []

    def publisher(self) -> EventPublisher:
        self.made.append(MemoryPublisher())
        return self.made[-1]

    def unreachable(self) -> EventPublisher:
        """A publisher whose log refuses every record."""
        return MemoryPublisher(fail_with=ConnectionError("the log is unreachable"))

    def read(self, count: int) -> list[tuple[bytes, bytes]]:
        return [kv for p in self.made for kv in p.records[self.topic]][:count]


class KafkaKit:
    def __init__(self, bootstrap: str) -> None:
        from confluent_kafka.admin import AdminClient, NewTopic

        self.bootstrap = bootstrap
        self.topic = f"contract-{uuid.uuid4().hex[:8]}"
        admin = AdminClient({"bootstrap.servers": bootstrap})  # held until the topic exists
        admin.create_topics([NewTopic(self.topic, 1, 1)])[self.topic].result(30)

    def publisher(self) -> EventPublisher:
        from mapservice.adapters.kafka_publisher import KafkaPublisher
        from mapservice.settings import Settings

        return KafkaPublisher(Settings(kafka_bootstrap=self.bootstrap), "contract")

    def unreachable(self) -> EventPublisher:
        """A publisher pointed at a port nothing listens on: every record times out
        (kafka_publisher.MESSAGE_TIMEOUT_MS, 10 s)."""
        from mapservice.adapters.kafka_publisher import KafkaPublisher
        from mapservice.local.embedded import free_port
        from mapservice.settings import Settings

        return KafkaPublisher(Settings(kafka_bootstrap=f"127.0.0.1:{free_port()}"), "contract")

    def read(self, count: int) -> list[tuple[bytes, bytes]]:
        from confluent_kafka import OFFSET_BEGINNING, Consumer, TopicPartition

        consumer = Consumer(
            {
                "bootstrap.servers": self.bootstrap,
                "group.id": f"{self.topic}-reader",
                "enable.auto.commit": False,
            }
        )
        consumer.assign([TopicPartition(self.topic, 0, OFFSET_BEGINNING)])
        got: list[tuple[bytes, bytes]] = []
        deadline = time.monotonic() + 30
        try:
            while len(got) < count and time.monotonic() < deadline:
                msg = consumer.poll(0.5)
                if msg is not None and msg.error() is None:
                    got.append((msg.key(), msg.value()))
        finally:
            consumer.close()
        return got


@pytest.fixture(
    params=[
        "memory",
        pytest.param("kafka", marks=[pytest.mark.integration, pytest.mark.timeout(120)]),
    ]
)
def kit(request) -> Iterator[MemoryKit | KafkaKit]:
    made = (
        MemoryKit()
        if request.param == "memory"
        else KafkaKit(request.getfixturevalue("apache_kafka"))
    )
    yield made
    # The publishers' librdkafka handles go with the test (an unreachable one would
    # otherwise log its refused connections until the process exits).
    gc.collect()


def test_records_are_in_the_log_in_order_once_each_callback_said_so(kit) -> None:
    publisher = kit.publisher()
    done: list[tuple[int, Exception | None]] = []
    records = [(b"robot-1", f"event {i}".encode()) for i in range(5)]
    for i, (key, value) in enumerate(records):
        publisher.publish(kit.topic, key, value, lambda err, i=i: done.append((i, err)))
    assert done == []  # callbacks run inside poll/flush, on the caller's thread
    assert publisher.flush(30) == 0
    publisher.poll(0)
    assert sorted(done, key=lambda d: d[0]) == [(i, None) for i in range(5)]
    assert kit.read(5) == records


def test_a_log_that_cannot_take_the_record_reports_the_error_once(kit) -> None:
    publisher = kit.unreachable()
    done: list[Exception | None] = []
    publisher.publish(kit.topic, b"robot-1", b"lost", done.append)
    deadline = time.monotonic() + 60
    while not done and time.monotonic() < deadline:
        publisher.flush(1.0)
    publisher.poll(0)
    assert len(done) == 1 and isinstance(done[0], Exception)
    assert publisher.flush(1.0) == 0  # nothing left waiting: the caller publishes it again
