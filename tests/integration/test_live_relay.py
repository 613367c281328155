"""The live stream across processes on Apache Kafka (the session's shared node): what the
processors' KafkaLivePublisher publishes reaches every API replica's KafkaLiveRelay.

Bounded: each test waits seconds at most (Apache Kafka answers a relay's waiting fetch
as soon as new messages arrive)."""

from __future__ import annotations

import threading
import time
import uuid

import pytest
from confluent_kafka import Producer
from confluent_kafka.admin import AdminClient, NewTopic

from mapservice.adapters.kafka_live_publisher import KafkaLivePublisher
from mapservice.adapters.kafka_live_relay import KafkaLiveRelay
from mapservice.adapters.kafka_topics import ensure_topics
from mapservice.core.live_messages import live_records
from mapservice.settings import Settings

WAIT_S = 15


@pytest.fixture(scope="module")
def kafka(apache_kafka):
    """Settings on the shared broker, with topic names of this module's own."""
    prefix = f"test-live-relay-{uuid.uuid4().hex[:8]}"
    settings = Settings(
        kafka_bootstrap=apache_kafka,
        **{
            field: f"{prefix}.{field}"
            for field in (
                "topic_chunk_events",
                "topic_pose_events",
                "topic_meta_events",
                "topic_dead_letter",
                "topic_live",
                "topic_annotation_events",
            )
        },
    )
    ensure_topics(settings)
    return settings


class Collector:
    """What one relay handed on, as (robotId, ts_ms) in arrival order."""

    def __init__(self) -> None:
        self.keys: list[tuple[str, int]] = []
        self.changed = threading.Condition()

    def __call__(self, messages: list[dict]) -> None:
        with self.changed:
            self.keys.extend((m["robotId"], m["ts_ms"]) for m in messages)
            self.changed.notify_all()

    def wait_for(self, count: int, timeout_s: float = WAIT_S) -> list[tuple[str, int]]:
        with self.changed:
            self.changed.wait_for(lambda: len(self.keys) >= count, timeout_s)
            return list(self.keys)


def started(settings: Settings, **kwargs) -> tuple[KafkaLiveRelay, Collector]:
    got = Collector()
    relay = KafkaLiveRelay(settings, got, **kwargs)
    relay.start()
    assert relay.assigned.wait(WAIT_S), "relay never read the live topic"
    return relay, got


def test_every_replica_gets_every_stored_batch_in_order_from_its_start_on(kafka, ev):
    """Two API relays each receive all published messages in order; a relay started later
    gets only what was published after it started."""
    publisher = KafkaLivePublisher(kafka)
    first, got_first = started(kafka)
    second, got_second = started(kafka)
    try:
        batches = [
            [ev.pose(f"rep-{b % 3}", 1_000 * b + i) for i in range(5)]
            + [ev.chunk("rep-c", 1_000 * b)]
            for b in range(10)
        ]
        for batch in batches:
            publisher.publish(batch)
        expected = [(e.robot_id, e.event_time_ms) for batch in batches for e in batch]
        assert got_first.wait_for(len(expected)) == expected
        assert got_second.wait_for(len(expected)) == expected

        late, got_late = started(kafka)
        try:
            publisher.publish([ev.pose("rep-late", 99_000)])
            assert got_late.wait_for(1) == [("rep-late", 99_000)]  # nothing from before it started
            assert got_first.wait_for(len(expected) + 1)[-1] == ("rep-late", 99_000)
        finally:
            late.stop()
    finally:
        first.stop()
        second.stop()
        publisher.close()


def test_a_bad_record_is_skipped_and_the_relay_goes_on(kafka, ev):
    """A record that is not live messages is counted and skipped; the next one arrives."""
    relay, got = started(kafka)
    producer = Producer(kafka.kafka_config())
    try:
        producer.produce(kafka.topic_live, value=b"{not a live record")
        producer.produce(kafka.topic_live, value=live_records([ev.pose("after-bad", 5)])[0])
        producer.flush(10)
        assert got.wait_for(1) == [("after-bad", 5)]
    finally:
        relay.stop()


def test_the_relay_reads_every_partition(kafka, ev):
    """On a multi-partition live topic (e.g. created by an operator) the relay reads all partitions."""
    settings = kafka.model_copy(update={"topic_live": kafka.topic_live + ".partitioned"})
    admin = AdminClient(settings.kafka_config())
    admin.create_topics([NewTopic(settings.topic_live, num_partitions=2)])[
        settings.topic_live
    ].result(10)
    relay, got = started(settings)
    producer = Producer(settings.kafka_config())
    try:
        for p in (0, 1):
            producer.produce(
                settings.topic_live, partition=p, value=live_records([ev.pose(f"p{p}", p)])[0]
            )
        producer.flush(10)
        assert sorted(got.wait_for(2)) == [("p0", 0), ("p1", 1)]
    finally:
        relay.stop()


def test_the_relay_waits_for_a_live_topic_that_does_not_exist_yet(kafka, ev):
    """An API started before the processors created the live topic starts relaying once it exists."""
    settings = kafka.model_copy(update={"topic_live": kafka.topic_live + ".later"})
    got = Collector()
    relay = KafkaLiveRelay(settings, got)
    relay.start()
    try:
        time.sleep(1.5)
        assert not relay.assigned.is_set()
        ensure_topics(settings)
        assert relay.assigned.wait(WAIT_S)
        publisher = KafkaLivePublisher(settings)
        publisher.publish([ev.pose("later", 7)])
        publisher.close()
        assert got.wait_for(1) == [("later", 7)]
    finally:
        relay.stop()
