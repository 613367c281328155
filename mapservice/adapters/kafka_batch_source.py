"""confluent-kafka consumer behind the EventSource port: records in batches, commits by hand.

Why not a faust agent for the history: faust hands records to agents one at a time
(a task pair per record, the conductor, the stream, the Monitor sensor): ~250 µs of CPU
per event here, against ~5 µs for `Consumer.consume(n)` (BENCHMARKS.md, "sink path").
At-least-once: offsets are committed only by `commit(records)`, after the caller stored
them; rebalance callbacks run inside `poll`, so they never fall between a batch's insert
and its commit.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence

import structlog
from confluent_kafka import Consumer, KafkaError, KafkaException, TopicPartition
from prometheus_client import Gauge

from mapservice.core.ports import SourceRecord
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

LAG = Gauge("mapservice_consumer_lag_records",
            "Records in a partition not yet consumed by this process (librdkafka's consumer_lag)",
            ["group", "topic", "partition"])
# librdkafka reports each partition's lag in its statistics (every STATS_INTERVAL_MS,
# delivered from inside consume()): no extra broker requests.
STATS_INTERVAL_MS = 5000


def consumer_config(settings: Settings, group_id: str) -> dict:
    session_ms = max(int(settings.kafka_rebalance_timeout_s * 1000), 10_000)
    return {
        **settings.kafka_config(),
        "group.id": group_id,
        "client.id": group_id,
        "auto.offset.reset": "earliest",
        "enable.auto.commit": False,
        "enable.auto.offset.store": False,
        # Same partition assignment story as faust's consumers: a join waits up to this
        # long, and tansu always waits the whole of it, so it is kept short. An insert
        # that stalls longer costs a rejoin and a re-delivery, never a loss.
        "session.timeout.ms": session_ms,
        "max.poll.interval.ms": session_ms,
        "heartbeat.interval.ms": 1000,
        # tansu answers an empty fetch only when this wait runs out, not when records
        # arrive, so librdkafka's 500 ms default added ~0.1-0.2 s to every event's
        # latency. Apache Kafka answers on arrival; there a short wait costs only idle
        # fetches.
        "fetch.wait.max.ms": settings.kafka_fetch_wait_ms,
        "statistics.interval.ms": STATS_INTERVAL_MS,
    }


def record_lag(group: str, stats_json: str) -> None:
    """Sets the lag gauge from one librdkafka statistics report (partitions this consumer
    fetches; librdkafka reports -1 until it knows, and the internal partition -1)."""
    stats = json.loads(stats_json)
    for topic, t in stats.get("topics", {}).items():
        for partition, p in t.get("partitions", {}).items():
            lag = p.get("consumer_lag", -1)
            if int(partition) >= 0 and p.get("fetch_state") == "active" and lag >= 0:
                LAG.labels(group, topic, partition).set(lag)


class KafkaBatchSource:
    """Created without I/O; `start()` subscribes."""

    def __init__(self, settings: Settings, topics: Sequence[str], group_id: str,
                 on_assigned: Callable[[list[tuple[str, int]]], None] | None = None) -> None:
        self.group_id = group_id
        self.config = {**consumer_config(settings, group_id),
                       "stats_cb": lambda stats: record_lag(group_id, stats),
                       "on_commit": self._committed}
        self.topics = list(topics)
        self.on_assigned = on_assigned
        self.on_commit_failed: Callable[[], None] | None = None  # an asynchronous commit failed
        self.consumer: Consumer | None = None

    def start(self) -> None:
        self.consumer = Consumer(self.config)
        self.consumer.subscribe(self.topics, on_assign=self._assigned, on_revoke=self._revoked)

    def _assigned(self, _consumer, partitions: list[TopicPartition]) -> None:
        log.info("history partitions assigned", count=len(partitions))
        for p in partitions:  # a series per owned partition from the start (0 until measured)
            LAG.labels(self.group_id, p.topic, str(p.partition)).set(0)
        if self.on_assigned is not None:
            self.on_assigned([(p.topic, p.partition) for p in partitions])

    def _revoked(self, _consumer, partitions: list[TopicPartition]) -> None:
        # Another replica owns them now and reports their lag.
        for p in partitions:
            try:
                LAG.remove(self.group_id, p.topic, str(p.partition))
            except KeyError:
                pass

    def poll(self, max_records: int, timeout_s: float) -> list[SourceRecord]:
        assert self.consumer is not None, "start() first"
        out = []
        for m in self.consumer.consume(max_records, timeout_s):
            err = m.error()
            if err is not None:
                if err.code() != KafkaError._PARTITION_EOF:
                    log.warning("kafka consumer error", error=str(err))
                continue
            out.append(SourceRecord(m.topic(), m.partition(), m.offset(), m.value() or b""))
        return out

    def commit(self, records: Sequence[SourceRecord]) -> bool:
        """Commits past the highest offset per partition, asynchronously: the next batch
        need not wait for the broker's answer (up to ~0.1 s under load). False if the
        consumer refused at once; a commit the broker refuses later (the group moved on)
        reaches `on_commit_failed`. Either way the records are delivered again to whoever
        owns their partitions, and the history's identities absorb the repeat."""
        assert self.consumer is not None, "start() first"
        last: dict[tuple[str, int], int] = {}
        for r in records:
            key = (r.topic, r.partition)
            if r.offset >= last.get(key, -1):
                last[key] = r.offset
        if not last:
            return True
        try:
            self.consumer.commit(offsets=[TopicPartition(t, p, o + 1) for (t, p), o in last.items()],
                                 asynchronous=True)
            return True
        except KafkaException as exc:
            log.warning("offset commit failed; the batch will be re-delivered", error=str(exc))
            return False

    def _committed(self, error, partitions: list[TopicPartition]) -> None:
        """librdkafka's answer to a commit, from inside `consume` or `close`."""
        failed = [p for p in partitions if p.error is not None]
        if error is None and not failed:
            return
        log.warning("offset commit failed; those records will be delivered again",
                    error=str(error or failed[0].error), partitions=len(failed) or len(partitions))
        if self.on_commit_failed is not None:
            self.on_commit_failed()

    def close(self) -> None:
        if self.consumer is not None:
            self.consumer.close()
            self.consumer = None
