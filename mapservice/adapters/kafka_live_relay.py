"""The API's side of the live stream: reads the live topic and hands its messages on.

Every API process reads every partition from its end (`assign`, no consumer group
membership, nothing committed): N replicas each see all messages, and a restarted
replica starts at now (its viewers re-seek from the store when they reconnect). The
service creates the topic with one partition; partitions added later are read after the
API's next restart.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable

import structlog
from confluent_kafka import Consumer, KafkaError, TopicPartition
from prometheus_client import Counter, Histogram

from mapservice.adapters.kafka_logs import logged
from mapservice.core.live_messages import BadLiveRecord, LiveText, live_record_texts
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

RELAY_LAG = Histogram(
    "mapservice_live_relay_lag_seconds",
    "From the processors' produce of a live record to this API reading it",
    buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5),
)
RELAY_BAD = Counter(
    "mapservice_live_relay_bad_records_total", "Live-topic records that were skipped"
)


def live_consumer_config(settings: Settings) -> dict:
    group = f"mapservice-api-live-{uuid.uuid4().hex[:12]}"  # never joins: assign() only
    return logged(
        {
            **settings.kafka_config(),
            "group.id": group,
            "client.id": group,
            "enable.auto.commit": False,
            "enable.auto.offset.store": False,
            "auto.offset.reset": "latest",
            # As the history's fetch waits (kafka_batch_source.py).
            "fetch.wait.max.ms": settings.kafka_fetch_wait_ms,
            "queued.max.messages.kbytes": 16 * 1024,
        }
    )


class KafkaLiveRelay:
    """Calls `on_messages(list_of_live_messages)` from its own thread, per polled batch."""

    def __init__(self, settings: Settings, on_messages: Callable[[list[LiveText]], None]) -> None:
        self.topic = settings.topic_live
        self.config = live_consumer_config(settings)
        self.on_messages = on_messages
        self.assigned = threading.Event()  # set once it reads every partition of the topic
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._since_ms = 0  # assignment time (wall clock, ms)
        self._caught_up: set[int] = set()  # partitions past their records from before it

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="live-relay", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _partitions(self, consumer: Consumer) -> set[int]:
        try:
            topic = consumer.list_topics(self.topic, timeout=5).topics.get(self.topic)
        except Exception as exc:  # Kafka not reachable yet: asked again
            log.warning("live topic metadata unavailable", topic=self.topic, error=str(exc))
            return set()
        if topic is None or topic.error is not None:
            return set()
        return set(topic.partitions)

    def _end_offset(self, consumer: Consumer, partition: int) -> int:
        """The partition's end as the broker reports it now (raises if it does not answer:
        `_run` starts over)."""
        _low, high = consumer.get_watermark_offsets(
            TopicPartition(self.topic, partition), timeout=5, cached=False
        )
        return high

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                self._follow()
            except Exception as exc:  # never stop relaying for good: start over
                self.assigned.clear()
                log.error("live relay failed; starting it again", error=str(exc))
                self._stopping.wait(1.0)

    def _follow(self) -> None:
        consumer = Consumer(self.config)
        try:
            partitions: set[int] = set()
            waited = False
            while not self._stopping.is_set() and not partitions:
                partitions = self._partitions(consumer)
                if not partitions:
                    if not waited:  # the processors create it; once is enough to say so
                        log.info("waiting for the live topic", topic=self.topic)
                        waited = True
                    self._stopping.wait(1.0)
            if not partitions:
                return
            # Where to start is asked now, not left to OFFSET_END: that is resolved at the
            # first fetch, after `assigned` is set, and a record produced in between was
            # behind the end it resolved to, i.e. never relayed (seen under load in CI).
            # tansu's end offset is the start of the partition's last record batch + 1,
            # so the first fetch can repeat that batch's older records: the first records
            # of each partition are skipped while produced before now (Apache Kafka
            # starts at the true end anyway).
            self._since_ms = time.time_ns() // 1_000_000
            consumer.assign(
                [
                    TopicPartition(self.topic, p, self._end_offset(consumer, p))
                    for p in sorted(partitions)
                ]
            )
            self._caught_up = set()
            self.assigned.set()
            log.info("live relay reading", topic=self.topic, partitions=len(partitions))
            while not self._stopping.is_set():
                # Not consume(n, timeout): that waits for n records or the timeout. The
                # first record is relayed at once, with whatever queued behind it.
                first = consumer.poll(0.5)
                if first is not None:
                    self._relay([first, *consumer.consume(999, 0)])
        finally:
            consumer.close()

    def _relay(self, records) -> None:
        messages: list = []
        now = time.time()
        for m in records:
            err = m.error()
            if err is not None:
                if err.code() != KafkaError._PARTITION_EOF:
                    log.warning("live relay consumer error", error=str(err))
                continue
            _kind, produced_ms = m.timestamp()
            if m.partition() not in self._caught_up:
                if 0 < produced_ms < self._since_ms:
                    continue  # from before this relay started (see _follow)
                self._caught_up.add(m.partition())
            if produced_ms > 0:
                RELAY_LAG.observe(max(0.0, now - produced_ms / 1000))
            try:
                # Kept as JSON text: the API sends each on as it came (core/live_messages.py).
                messages.extend(live_record_texts(m.value() or b""))
            except BadLiveRecord as exc:
                RELAY_BAD.inc()
                log.warning(
                    "live record skipped",
                    partition=m.partition(),
                    offset=m.offset(),
                    reason=str(exc),
                )
        if messages:
            self.on_messages(messages)
