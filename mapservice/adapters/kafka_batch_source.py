"""confluent-kafka consumer behind the EventSource port: records in batches, commits by hand.

Why not a faust agent for the history: faust hands records to agents one at a time
(a task pair per record, the conductor, the stream, the Monitor sensor): ~250 µs of CPU
per event here, against ~5 µs for `Consumer.consume(n)` (BENCHMARKS.md, "sink path").
At-least-once: offsets are committed only by `commit(records)`, after the caller stored
them, and only for records this member was handed since the group last changed (below).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence

import structlog
from confluent_kafka import Consumer, KafkaError, KafkaException, TopicPartition
from prometheus_client import Counter, Gauge

from mapservice.adapters.kafka_logs import logged
from mapservice.core.ports import SourceRecord
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

LAG = Gauge(
    "mapservice_consumer_lag_records",
    "Records in a partition not yet consumed by this process (librdkafka's consumer_lag)",
    ["group", "topic", "partition"],
)
# librdkafka reports each partition's lag in its statistics (every STATS_INTERVAL_MS,
# delivered from inside consume()): no extra broker requests.
STATS_INTERVAL_MS = 5000
# An event topic's offsets are contiguous (no compaction, no transactions), so there a record
# past the next expected offset means records this consumer has not seen (a compacted topic,
# such as the map meta's, has gaps by design and is not checked). tansu makes that
# happen: with two producers writing one partition, a batch can become readable after a
# later one, and a reader already past it never gets it (docs/embedded.md). The
# partition is read again from the first missing offset, up to GAP_REREADS times in a row;
# a gap still there after that is taken as real (records deleted under the reader) and logged.
GAP_REREADS = 5
# A paused poll hands out nothing; any it returns anyway (fetched before the pause) are
# sought back to. Up to this many per call.
STAY_MAX_RECORDS = 1000
OFFSET_GAPS = Counter(
    "mapservice_consumer_offset_gaps_total",
    "Jumps past unseen offsets: read again, or accepted after GAP_REREADS tries",
    ["outcome"],
)
# A commit is made only for records delivered in the current group membership, and only
# while librdkafka still holds the member id that membership began with. The caller may
# commit a batch long after it was polled (a ClickHouse outage; the pose views' interval),
# and by then the group may have moved on. Apache Kafka would refuse such a commit from a
# stale member, but a member that left the group (a missed poll interval, a broker that
# forgot it) commits as a plain consumer, and every broker takes that. Against a tansu
# restarted empty (memory storage) those offsets point past the new log's records: the
# group's next assignment would start there and skip them
# (tests/integration/test_tansu_restart.py).
NEVER_COMMITTED = -1  # records polled while the group changed that could not be read again
READ_AGAIN = Counter(
    "mapservice_consumer_read_again_after_rebalance_total",
    "Batches polled while the consumer group changed, read again under the new membership "
    "(never handed out: they could not be committed)",
)
STALE_COMMITS = Counter(
    "mapservice_consumer_stale_commits_total",
    "Commits not made: their records were delivered before the group "
    "changed (they will be delivered again)",
)


def consumer_config(settings: Settings, group_id: str) -> dict:
    # How long between polls before the member leaves its group: work longer than this (a
    # stalled insert, a rebuild) keeps it in with `stay_in_group`. The session
    # (heartbeats, sent by librdkafka's own thread) may be shorter.
    poll_ms = max(int(settings.kafka_rebalance_timeout_s * 1000), 10_000)
    session_ms = int(
        max(settings.kafka_rebalance_timeout_s, settings.kafka_session_timeout_s) * 1000
    )
    if settings.kafka_group_protocol == "consumer":
        # KIP-848: the broker assigns and holds the session timeout and the heartbeat
        # interval (group.consumer.session.timeout.ms, ...heartbeat.interval.ms; the
        # embedded broker sets them as below), and librdkafka refuses both settings here.
        return {
            **_common_config(settings, group_id),
            "group.protocol": "consumer",
            "max.poll.interval.ms": poll_ms,
        }
    return {
        **_common_config(settings, group_id),
        # Same partition assignment story as faust's consumers: a join waits up to this
        # long, and tansu always waits the whole of it, so it is kept short. An insert
        # that stalls longer costs a rejoin and a re-delivery, never a loss.
        "session.timeout.ms": session_ms,
        "max.poll.interval.ms": max(poll_ms, session_ms),
        "heartbeat.interval.ms": 1000,
    }


def _common_config(settings: Settings, group_id: str) -> dict:
    return logged(
        {
            **settings.kafka_config(),
            "group.id": group_id,
            "client.id": group_id,
            "auto.offset.reset": "earliest",
            "enable.auto.commit": False,
            "enable.auto.offset.store": False,
            # Apache Kafka answers a waiting fetch as soon as records arrive: a long wait
            # costs no latency, a short one idle fetches (the broker's CPU while the plant
            # is quiet). tansu answers only when the wait runs out: the embedded tansu's
            # components are given a short one (local/stack_env.py).
            "fetch.wait.max.ms": settings.kafka_fetch_wait_ms,
            "statistics.interval.ms": STATS_INTERVAL_MS,
        }
    )


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

    def __init__(
        self,
        settings: Settings,
        topics: Sequence[str],
        group_id: str,
        on_assigned: Callable[[list[tuple[str, int]]], None] | None = None,
        contiguous_topics: Sequence[str] | None = None,
    ) -> None:
        self.group_id = group_id
        self.config = {
            **consumer_config(settings, group_id),
            "stats_cb": lambda stats: record_lag(group_id, stats),
            "on_commit": self._committed,
        }
        self.topics = list(topics)
        self.on_assigned = on_assigned
        self.on_commit_failed: Callable[[], None] | None = None  # an asynchronous commit failed
        self.consumer: Consumer | None = None
        # Topics whose offset gaps are read again (default: all of `topics`).
        self.contiguous_topics = set(topics if contiguous_topics is None else contiguous_topics)
        self._next_offset: dict[tuple[str, int], int] = {}  # per partition, once one was read
        self._rereads: dict[tuple[str, int], int] = {}  # rereads in a row of a partition's gap
        self._membership = 0  # counts assignments and revocations (SourceRecord.membership)
        self._member_id: str | None = None  # librdkafka's, when the partitions were assigned
        # Partitions `stay_in_group` paused that the group took away before it could resume
        # them: librdkafka keeps a partition's pause through its revocation and a later
        # assignment (confluentinc/librdkafka#1849), so they are resumed once assigned again.
        self._left_paused: set[tuple[str, int]] = set()

    def start(self) -> None:
        self.consumer = Consumer(self.config)
        self.consumer.subscribe(self.topics, on_assign=self._assigned, on_revoke=self._revoked)

    def _assigned(self, consumer, partitions: list[TopicPartition]) -> None:
        log.info("history partitions assigned", count=len(partitions))
        self._membership += 1
        self._member_id = consumer.memberid()
        self._forget(partitions)  # reading starts wherever the group's offsets say
        for p in partitions:  # a series per owned partition from the start (0 until measured)
            LAG.labels(self.group_id, p.topic, str(p.partition)).set(0)
        if self.on_assigned is not None:
            self.on_assigned([(p.topic, p.partition) for p in partitions])

    def _revoked(self, _consumer, partitions: list[TopicPartition]) -> None:
        # Another replica owns them now and reports their lag.
        self._membership += 1
        self._forget(partitions)
        for p in partitions:
            try:
                LAG.remove(self.group_id, p.topic, str(p.partition))
            except KeyError:
                pass

    def _forget(self, partitions: list[TopicPartition]) -> None:
        for p in partitions:
            self._next_offset.pop((p.topic, p.partition), None)
            self._rereads.pop((p.topic, p.partition), None)

    def poll(self, max_records: int, timeout_s: float) -> list[SourceRecord]:
        assert self.consumer is not None, "start() first"
        out = []
        rewound: set[tuple[str, int]] = set()  # partitions read again: the rest comes again too
        before = self._membership
        if self._left_paused:
            self._resume_left_paused()
        messages = self.consumer.consume(max_records, timeout_s)
        # Rebalance callbacks run inside consume(), and the batch may hold records fetched
        # on either side of them: such a batch can never be committed. Handed out, its
        # records would be stored and left uncommitted; in a partition no later record
        # reaches (a chunk written once) the group's offset would then never pass them, and
        # every later join would deliver them again, until one after the retention dropped
        # their day brings that day back. So its partitions are read again, under the new
        # membership; only where that fails is it handed out uncommittable.
        membership = self._membership
        if self._membership != before:
            if self._read_again(messages):
                return []
            membership = NEVER_COMMITTED
        for m in messages:
            err = m.error()
            if err is not None:
                if err.code() != KafkaError._PARTITION_EOF:
                    log.warning("kafka consumer error", error=str(err))
                continue
            if m.topic() not in self.contiguous_topics:
                out.append(
                    SourceRecord(m.topic(), m.partition(), m.offset(), m.value() or b"", membership)
                )
                continue
            key = (m.topic(), m.partition())
            if key in rewound:
                continue
            expected = self._next_offset.get(key)
            if (
                expected is not None
                and m.offset() > expected
                and self._reread(key, expected, m.offset())
            ):
                rewound.add(key)
                continue
            if self._rereads and m.offset() == expected:
                self._rereads.pop(key, None)  # the gap is filled: a later one starts afresh
            self._next_offset[key] = m.offset() + 1
            out.append(
                SourceRecord(m.topic(), m.partition(), m.offset(), m.value() or b"", membership)
            )
        return out

    def stay_in_group(self) -> None:
        """A poll with every owned partition paused: max.poll.interval.ms counts from the
        last poll, so a member whose batch or rebuild takes longer than it would leave the
        group and, rejoined, rebuild again. Kafka's own way for long work between polls.
        Records pausing leaves in the queue (fetched before) are read again, not handed out."""
        assert self.consumer is not None, "start() first"
        paused = self.consumer.assignment()
        self.consumer.pause(paused)
        try:
            messages = self.consumer.consume(STAY_MAX_RECORDS, 0)
            taken = [m for m in messages if m.error() is None]
            if taken:
                self._read_again(taken)
        finally:
            # A rebalance inside that consume may have taken partitions away: resumed when
            # the group hands them back, or a partition paused for good stops the history.
            owned = {(tp.topic, tp.partition) for tp in self.consumer.assignment()}
            self.consumer.resume([tp for tp in paused if (tp.topic, tp.partition) in owned])
            self._left_paused |= {(tp.topic, tp.partition) for tp in paused} - owned
            if self._left_paused:
                self._resume_left_paused()

    def _resume_left_paused(self) -> None:
        """Resumes the partitions `stay_in_group` left paused that this member owns again."""
        back = [
            tp for tp in self.consumer.assignment() if (tp.topic, tp.partition) in self._left_paused
        ]
        if back:
            self.consumer.resume(back)
            self._left_paused -= {(tp.topic, tp.partition) for tp in back}
            log.info("partitions paused before the group changed resumed", count=len(back))

    def _read_again(self, messages: list) -> bool:
        """Seeks each partition of `messages` this member still owns back to its first
        offset among them (the others are another member's now); False if a seek failed."""
        first: dict[tuple[str, int], int] = {}
        for m in messages:
            if m.error() is None:
                key = (m.topic(), m.partition())
                first[key] = min(first.get(key, m.offset()), m.offset())
        try:
            owned = {(tp.topic, tp.partition) for tp in self.consumer.assignment()}
            for key, offset in first.items():
                if key in owned:
                    self.consumer.seek(TopicPartition(key[0], key[1], offset))
        except KafkaException as exc:
            log.warning(
                "could not read again a batch polled while the consumer group changed; "
                "its records are stored but not committed",
                error=str(exc),
            )
            return False
        self._forget([TopicPartition(t, p) for t, p in first])
        if first:
            READ_AGAIN.inc()
        return True

    def _reread(self, key: tuple[str, int], expected: int, got: int) -> bool:
        """Seeks a partition back to its first unseen offset; False once the same gap was
        read again GAP_REREADS times (or the seek fails): then it is accepted."""
        rereads = self._rereads.get(key, 0)
        if rereads < GAP_REREADS:
            try:
                self.consumer.seek(TopicPartition(key[0], key[1], expected))
                self._rereads[key] = rereads + 1
                OFFSET_GAPS.labels("reread").inc()
                return True
            except KafkaException as exc:
                log.warning(
                    "could not read an offset gap again",
                    topic=key[0],
                    partition=key[1],
                    error=str(exc),
                )
        self._rereads.pop(key, None)
        OFFSET_GAPS.labels("accepted").inc()
        log.warning(
            "offset gap accepted: records before it were not read",
            topic=key[0],
            partition=key[1],
            expected=expected,
            got=got,
            missing=got - expected,
        )
        return False

    def commit(self, records: Sequence[SourceRecord]) -> bool:
        """Commits past the highest offset per partition, asynchronously: the next batch
        need not wait for the broker's answer (up to ~0.1 s under load). False if the
        group changed since some of the records were delivered (STALE_COMMITS: only the
        others are committed) or the consumer refused at once; a commit the broker refuses
        later (the group moved on) reaches `on_commit_failed`. What is not committed is
        covered by a later commit of its partition or delivered again to whoever owns it,
        and the history's identities absorb the repeat."""
        assert self.consumer is not None, "start() first"
        left_group = self.consumer.memberid() != self._member_id
        current = [] if left_group else [r for r in records if r.membership == self._membership]
        if len(current) < len(records):
            STALE_COMMITS.inc()
            log.warning(
                "not committing offsets delivered before the consumer group changed; "
                "those records will be delivered again",
                left_group=left_group,
                records=len(records) - len(current),
            )
        return self._commit(current) and len(current) == len(records)

    def _commit(self, records: Sequence[SourceRecord]) -> bool:
        last: dict[tuple[str, int], int] = {}
        for r in records:
            key = (r.topic, r.partition)
            if r.offset >= last.get(key, -1):
                last[key] = r.offset
        if not last:
            return True
        try:
            self.consumer.commit(
                offsets=[TopicPartition(t, p, o + 1) for (t, p), o in last.items()],
                asynchronous=True,
            )
            return True
        except KafkaException as exc:
            log.warning("offset commit failed; the batch will be re-delivered", error=str(exc))
            return False

    def _committed(self, error, partitions: list[TopicPartition]) -> None:
        """librdkafka's answer to a commit, from inside `consume` or `close`."""
        failed = [p for p in partitions if p.error is not None]
        if error is None and not failed:
            return
        log.warning(
            "offset commit failed; those records will be delivered again",
            error=str(error or failed[0].error),
            partitions=len(failed) or len(partitions),
        )
        if self.on_commit_failed is not None:
            self.on_commit_failed()

    def close(self) -> None:
        if self.consumer is not None:
            self.consumer.close()
            self.consumer = None
