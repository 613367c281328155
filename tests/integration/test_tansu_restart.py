"""Kafka clients across a tansu restart (tansu keeps its log in memory: restarted, it is a
new, empty Kafka): the publisher renews its stuck idempotent producer and delivers every
record; offsets read from the old log are not committed to the new one. The fault tests
(test_faults.py) rely on both where the stacks fall back to tansu."""

from __future__ import annotations

import os
import signal
import time

from mapservice.local import embedded

# ---- the Kafka producer across a tansu restart -------------------------------------------


def test_a_publisher_delivers_again_after_tansu_restarted_empty(tmp_path) -> None:
    """After tansu restarts empty, the publisher renews its stuck producer and every record is delivered."""
    # A restarted tansu has no producer state: the idempotent producer gets
    # UNKNOWN_PRODUCER_ID forever (or a fatal error); records time out after 10 s.
    from mapservice.adapters.kafka_publisher import MESSAGE_TIMEOUT_MS, KafkaPublisher
    from mapservice.adapters.kafka_topics import ensure_topics
    from mapservice.settings import Settings

    port = embedded.free_port()
    settings = Settings(kafka_bootstrap=f"127.0.0.1:{port}", data_dir=tmp_path)
    tansu = embedded.start_tansu(port)
    publisher = KafkaPublisher(settings, client_id="renewal-test")
    delivered: list[int] = []

    def publish(n: int) -> None:
        def done(error) -> None:  # as the gateway does: never drop, produce again
            if error is None:
                delivered.append(n)
            else:
                publisher.publish(settings.topic_pose_events, b"k%d" % n, b"v", done)

        publisher.publish(settings.topic_pose_events, b"k%d" % n, b"v", done)

    try:
        ensure_topics(settings)
        for n in range(20):
            publish(n)
        assert publisher.flush(10) == 0 and sorted(delivered) == list(range(20))
        os.killpg(tansu.pid, signal.SIGKILL)
        tansu.wait(10)
        tansu = embedded.start_tansu(port)
        ensure_topics(settings)
        started = time.monotonic()
        for n in range(20, 40):
            publish(n)
        deadline = started + MESSAGE_TIMEOUT_MS / 1000 + 15
        while len(set(delivered)) < 40 and time.monotonic() < deadline:
            publisher.poll(0.1)
        assert set(delivered) == set(range(40)), sorted(set(range(40)) - set(delivered))
    finally:
        publisher.flush(1)
        os.killpg(tansu.pid, signal.SIGKILL)
        tansu.wait(10)


# ---- the history's consumer across a tansu restart ---------------------------------------


def poll_until(source, count: int, timeout_s: float) -> list:
    records: list = []
    deadline = time.monotonic() + timeout_s
    while len(records) < count and time.monotonic() < deadline:
        records += source.poll(100, 0.5)
    return records


def test_offsets_read_before_tansu_restarted_empty_are_not_committed_to_the_new_one(
    tmp_path,
) -> None:
    """Offsets polled from a tansu that then restarted empty are not committed with the new log's: the group resumes where the new log was read to."""
    # As in the split deployment's Kafka-while-ClickHouse-down fault: the history consumer
    # stores a batch polled from the old tansu only once ClickHouse is back, by when it may
    # have been assigned the new, empty tansu's partitions; it commits both together.
    # Committed there, the old (higher) offsets are where the group next starts: past the
    # new log's records.
    from confluent_kafka import Producer

    from mapservice.adapters.kafka_batch_source import KafkaBatchSource
    from mapservice.adapters.kafka_topics import ensure_topics
    from mapservice.settings import Settings

    port = embedded.free_port()
    settings = Settings(kafka_bootstrap=f"127.0.0.1:{port}", data_dir=tmp_path)
    topic = settings.topic_pose_events
    producer = Producer(settings.kafka_config())

    def produce(n: int) -> None:
        for i in range(n):
            producer.produce(topic, b"v%d" % i, partition=0)
        assert producer.flush(10) == 0

    def offsets(records) -> list[int]:
        return [r.offset for r in records if r.partition == 0]

    tansu = embedded.start_tansu(port)
    sources = [KafkaBatchSource(settings, [topic], "restart-commit-test")]
    try:
        ensure_topics(settings)
        produce(30)
        sources[0].start()
        before = poll_until(sources[0], 30, 60)
        assert offsets(before) == list(range(30))
        os.killpg(tansu.pid, signal.SIGKILL)
        tansu.wait(10)
        tansu = embedded.start_tansu(port)
        ensure_topics(settings)
        produce(10)
        after = poll_until(sources[0], 10, 60)  # the new group's assignment: offsets from 0
        produce(10)
        after += poll_until(sources[0], 10, 30)
        assert offsets(after) == list(range(20))
        assert sources[0].commit(before + after) is False  # only the new log's offsets
        produce(10)
        sources[0].close()
        sources.append(KafkaBatchSource(settings, [topic], "restart-commit-test"))
        sources[1].start()
        assert offsets(poll_until(sources[1], 10, 40)) == list(range(20, 30))
    finally:
        for source in sources:
            source.close()
        os.killpg(tansu.pid, signal.SIGKILL)
        tansu.wait(10)
