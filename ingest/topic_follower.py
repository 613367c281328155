"""The shape of the gateway's Kafka readers (the command relay, the meta watcher): one
daemon thread reads a whole topic, every partition assigned (no consumer group membership,
nothing committed), from where the reader says, and hands each record's value on until
stopped."""

from __future__ import annotations

import threading

from confluent_kafka import Consumer, TopicPartition

from mapservice.adapters.kafka_logs import logged
from mapservice.settings import Settings


class TopicFollower:
    """Subclasses say where each partition starts (`_start_offsets`), what a record's value
    does (`_on_record`) and, in `_run`, what a failed `_read` leads to."""

    thread_name = "topic-follower"
    group_id = "mapservice-topic-follower"  # never joined (assign only); Kafka wants one
    poll_s = 0.5  # how soon a stop is noticed while the topic is quiet

    def __init__(self, settings: Settings, topic: str) -> None:
        self.settings = settings
        self.topic = topic
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        """The thread's body: one read, until stopped or failed."""
        self._read()

    def _start_offsets(self, consumer: Consumer, partitions: list[int]) -> list[TopicPartition]:
        raise NotImplementedError

    def _on_record(self, value: bytes | None) -> None:
        raise NotImplementedError

    def _read(self) -> None:
        """Reads the topic until stopped; raises what the consumer raises (Kafka away)."""
        consumer = Consumer(
            logged(
                {
                    **self.settings.kafka_config(),
                    "group.id": self.group_id,
                    "enable.auto.commit": False,
                }
            )
        )
        try:
            md = consumer.list_topics(self.topic, timeout=30)
            parts = sorted(md.topics[self.topic].partitions) if self.topic in md.topics else [0]
            consumer.assign(self._start_offsets(consumer, parts))
            while not self._stop.is_set():
                msg = consumer.poll(self.poll_s)
                if msg is None or msg.error():
                    continue
                self._on_record(msg.value())
        finally:
            consumer.close()
