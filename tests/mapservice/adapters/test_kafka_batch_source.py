"""KafkaBatchSource's consumer settings (the consumer itself runs in the integration tests)."""

from __future__ import annotations

import pytest

from mapservice.adapters.kafka_batch_source import KafkaBatchSource, consumer_config
from mapservice.settings import Settings


def test_consumer_commits_by_hand_and_fetches_with_the_configured_wait() -> None:
    """Offsets are never auto-committed or auto-stored, and fetch.wait.max.ms comes from
    the settings (default 500 ms: Apache Kafka answers on arrival; a stack on the embedded
    tansu sets 50, tests/mapservice/local/test_stack.py)."""
    conf = consumer_config(Settings(kafka_fetch_wait_ms=40), "history")
    assert conf["enable.auto.commit"] is False and conf["enable.auto.offset.store"] is False
    assert conf["fetch.wait.max.ms"] == 40
    assert consumer_config(Settings(), "history")["fetch.wait.max.ms"] == 500


def test_the_consumer_group_protocol_leaves_session_and_heartbeat_to_the_broker() -> None:
    """Classic (the default) sets the member's session timeout and heartbeat; with Kafka 4's
    consumer protocol (KIP-848) the broker holds both, and librdkafka refuses a consumer
    that sets them: the configuration must create a consumer."""
    from confluent_kafka import Consumer

    classic = consumer_config(Settings(kafka_bootstrap="127.0.0.1:1"), "history")
    assert Settings().kafka_group_protocol == "classic"
    assert "group.protocol" not in classic and classic["session.timeout.ms"] == 10_000
    new = consumer_config(
        Settings(kafka_bootstrap="127.0.0.1:1", kafka_group_protocol="consumer"), "history"
    )
    assert new["group.protocol"] == "consumer"
    assert "session.timeout.ms" not in new and "heartbeat.interval.ms" not in new
    assert new["enable.auto.commit"] is False and new["fetch.wait.max.ms"] == 500
    Consumer(new).close()


def test_the_session_timeout_is_a_setting_apart_from_the_poll_interval() -> None:
    """A short session (a dead replica's partitions move sooner) leaves the poll interval
    (how long a stalled insert may hold a batch before the member leaves) at 10 s or the
    rebalance timeout; a rebalance timeout beyond the session lengthens both."""
    for session_s, rebalance_s in [(3.0, 0.5), (3.0, 3.0), (4.0, 5.0), (10.0, 3.0), (45.0, 30.0)]:
        conf = consumer_config(
            Settings(kafka_session_timeout_s=session_s, kafka_rebalance_timeout_s=rebalance_s),
            "history",
        )
        assert conf["session.timeout.ms"] == int(max(session_s, rebalance_s) * 1000)
        assert conf["max.poll.interval.ms"] == max(10_000, conf["session.timeout.ms"]), conf
        assert conf["heartbeat.interval.ms"] * 3 <= conf["session.timeout.ms"], conf


def test_constructing_the_source_opens_no_consumer() -> None:
    """No network I/O in the constructor: the consumer is created by start()."""
    source = KafkaBatchSource(Settings(kafka_bootstrap="127.0.0.1:1"), ["t"], "g")
    assert source.consumer is None and source.config["group.id"] == "g"


def lag(group: str, topic: str, partition: str) -> float | None:
    from prometheus_client import REGISTRY

    return REGISTRY.get_sample_value(
        "mapservice_consumer_lag_records", {"group": group, "topic": topic, "partition": partition}
    )


def test_statistics_set_the_lag_of_each_fetched_partition() -> None:
    """A librdkafka statistics report sets the lag per active partition, skipping unknown (-1) lags and partition -1."""
    import json

    from mapservice.adapters.kafka_batch_source import record_lag

    stats = {
        "topics": {
            "poses": {
                "partitions": {
                    "0": {"consumer_lag": 42, "fetch_state": "active"},
                    "1": {"consumer_lag": -1, "fetch_state": "active"},
                    "2": {"consumer_lag": 7, "fetch_state": "none"},
                    "-1": {"consumer_lag": 9, "fetch_state": "active"},
                }
            }
        }
    }
    record_lag("lag-test", json.dumps(stats))
    assert lag("lag-test", "poses", "0") == 42
    assert lag("lag-test", "poses", "1") is None and lag("lag-test", "poses", "2") is None
    assert lag("lag-test", "poses", "-1") is None


def test_assignment_creates_and_revocation_removes_the_lag_series() -> None:
    """An assigned partition reports lag 0 at once; a revoked one stops being reported by this process."""
    from confluent_kafka import TopicPartition

    source = KafkaBatchSource(Settings(), ["t"], "lag-assign")
    assert source.config["statistics.interval.ms"] > 0 and callable(source.config["stats_cb"])
    source._assigned(_ScriptedConsumer([]), [TopicPartition("t", 3)])
    assert lag("lag-assign", "t", "3") == 0
    source._revoked(_ScriptedConsumer([]), [TopicPartition("t", 3)])
    assert lag("lag-assign", "t", "3") is None


def test_a_commit_the_broker_refuses_later_is_reported() -> None:
    """Commits are asynchronous; librdkafka's later refusal reaches on_commit_failed, a success does not."""
    from confluent_kafka import KafkaError, TopicPartition

    source = KafkaBatchSource(Settings(kafka_bootstrap="127.0.0.1:1"), ["t"], "g")
    failures = []
    source.on_commit_failed = lambda: failures.append(1)
    assert source.config["on_commit"] == source._committed
    source.config["on_commit"](None, [TopicPartition("t", 0, 5)])
    assert failures == []
    source.config["on_commit"](
        KafkaError(KafkaError.REBALANCE_IN_PROGRESS), [TopicPartition("t", 0, 5)]
    )
    assert failures == [1]


class _Message:
    def __init__(self, partition: int, offset: int, topic: str = "t") -> None:
        self._p, self._o, self._t = partition, offset, topic

    def error(self):
        return None

    def topic(self) -> str:
        return self._t

    def partition(self) -> int:
        return self._p

    def offset(self) -> int:
        return self._o

    def value(self) -> bytes:
        return b"%d:%d" % (self._p, self._o)


class _ScriptedConsumer:
    """consume() hands out the next scripted batch; seek() and commit() are recorded;
    memberid() is librdkafka's member id, set by the test."""

    def __init__(self, batches: list[list[tuple[int, int]]]) -> None:
        self.batches = [[_Message(p, o) for p, o in b] for b in batches]
        self.seeks: list[tuple[int, int]] = []
        self.commits: list[list[tuple[int, int]]] = []
        self.member_id = "member-1"
        self.owned = [0, 1]  # the partitions of "t" assigned to this member
        self.seek_fails = False

    def assignment(self):
        from confluent_kafka import TopicPartition

        return [TopicPartition("t", p) for p in self.owned]

    def consume(self, _n, _timeout):
        return self.batches.pop(0) if self.batches else []

    def seek(self, tp) -> None:
        if self.seek_fails:
            from confluent_kafka import KafkaError, KafkaException

            raise KafkaException(KafkaError(KafkaError._STATE))
        self.seeks.append((tp.partition, tp.offset))

    def memberid(self) -> str:
        return self.member_id

    def commit(self, offsets, asynchronous: bool) -> None:
        self.commits.append([(tp.partition, tp.offset) for tp in offsets])


def _source(batches) -> KafkaBatchSource:
    source = KafkaBatchSource(Settings(kafka_bootstrap="127.0.0.1:1"), ["t"], "g")
    source.consumer = _ScriptedConsumer(batches)
    return source


def _assigned_source(batches) -> KafkaBatchSource:
    """A source the group has assigned its partitions (as member-1)."""
    from confluent_kafka import TopicPartition

    source = _source(batches)
    source._assigned(source.consumer, [TopicPartition("t", 0), TopicPartition("t", 1)])
    return source


def offsets(records) -> list[tuple[int, int]]:
    return [(r.partition, r.offset) for r in records]


def test_an_offset_gap_is_read_again_and_each_record_handed_out_once_in_order() -> None:
    """Partition 0 jumps from 11 to 14 (a batch tansu showed late): the source seeks back to 12,
    drops what followed the gap, keeps partition 1, and the next poll brings 12 to 15."""
    source = _source(
        [[(0, 10), (0, 11), (1, 5), (0, 14), (0, 15), (1, 6)], [(0, 12), (0, 13), (0, 14), (0, 15)]]
    )
    first = source.poll(100, 0.1)
    assert offsets(first) == [(0, 10), (0, 11), (1, 5), (1, 6)]
    assert source.consumer.seeks == [(0, 12)]
    assert offsets(source.poll(100, 0.1)) == [(0, 12), (0, 13), (0, 14), (0, 15)]


def test_a_gap_that_stays_is_accepted_after_the_rereads_and_logged(caplog) -> None:
    """Offsets 12-13 never come: after GAP_REREADS seeks the records after the gap are handed out."""
    from mapservice.adapters.kafka_batch_source import GAP_REREADS

    source = _source([[(0, 11)]] + [[(0, 14)]] * (GAP_REREADS + 1))
    assert offsets(source.poll(100, 0.1)) == [(0, 11)]
    for _ in range(GAP_REREADS):
        assert source.poll(100, 0.1) == []
    assert offsets(source.poll(100, 0.1)) == [(0, 14)]
    assert source.consumer.seeks == [(0, 12)] * GAP_REREADS


def test_a_filled_gap_does_not_count_toward_the_next_one() -> None:
    """Two gaps, each filled after one reread: neither is accepted, both are read again."""
    source = _source([[(0, 1), (0, 3)], [(0, 2), (0, 3), (0, 5)], [(0, 4), (0, 5)]])
    assert offsets(source.poll(100, 0.1)) == [(0, 1)]
    assert offsets(source.poll(100, 0.1)) == [(0, 2), (0, 3)]
    assert offsets(source.poll(100, 0.1)) == [(0, 4), (0, 5)]
    assert source.consumer.seeks == [(0, 2), (0, 4)]


def test_a_newly_assigned_partition_starts_wherever_the_group_left_it() -> None:
    """After a reassignment the first record sets the expectation again: no seek for a jump."""
    from confluent_kafka import TopicPartition

    source = _source([[(0, 1)], [(0, 40)]])
    assert offsets(source.poll(100, 0.1)) == [(0, 1)]
    source._assigned(source.consumer, [TopicPartition("t", 0)])
    assert offsets(source.poll(100, 0.1)) == [(0, 40)] and source.consumer.seeks == []


def test_a_compacted_topics_gaps_are_not_read_again() -> None:
    """A topic left out of contiguous_topics (the compacted map meta) jumps without a seek."""
    source = KafkaBatchSource(
        Settings(kafka_bootstrap="127.0.0.1:1"), ["t", "meta"], "g", contiguous_topics=["t"]
    )
    consumer = _ScriptedConsumer([])
    consumer.batches = [[_Message(0, 3, "meta"), _Message(0, 9, "meta"), _Message(0, 1, "t")]]
    source.consumer = consumer
    assert [(r.topic, r.offset) for r in source.poll(100, 0.1)] == [
        ("meta", 3),
        ("meta", 9),
        ("t", 1),
    ]
    assert consumer.seeks == []


def test_a_commit_covers_the_highest_offset_of_each_partition_delivered_in_this_membership() -> (
    None
):
    """Records polled since the last assignment are committed past each partition's highest offset."""
    source = _assigned_source([[(0, 4), (1, 9), (0, 5)]])
    assert source.commit(source.poll(100, 0.1)) is True
    assert source.consumer.commits == [[(0, 6), (1, 10)]]


def test_records_delivered_before_a_reassignment_are_not_committed_after_it() -> None:
    """A rebalance between poll and commit: the earlier records' offsets are dropped (they
    may be another member's now, or point into a log the broker lost), the later ones committed."""
    from confluent_kafka import TopicPartition

    source = _assigned_source([[(0, 700), (1, 800)], [(0, 3)]])
    before = source.poll(100, 0.1)
    source._revoked(source.consumer, [TopicPartition("t", 0), TopicPartition("t", 1)])
    source._assigned(source.consumer, [TopicPartition("t", 0)])
    after = source.poll(100, 0.1)
    assert source.commit(before + after) is False
    assert source.consumer.commits == [[(0, 4)]]
    assert source.commit(before) is False and source.consumer.commits == [[(0, 4)]]


def test_nothing_is_committed_once_the_consumer_has_left_its_group() -> None:
    """librdkafka dropped the member id (a missed poll interval, a broker that forgot the
    member) before the rebalance callbacks ran: no commit, since it would be taken as a
    plain consumer's."""
    source = _assigned_source([[(0, 7)]])
    records = source.poll(100, 0.1)
    source.consumer.member_id = ""
    assert source.commit(records) is False and source.consumer.commits == []


def _rebalancing(source: KafkaBatchSource, owned: list[int]):
    """Makes the next consume() run an assignment of `owned` inside it, as librdkafka does."""
    from confluent_kafka import TopicPartition

    consume = source.consumer.consume

    def consume_with_a_rebalance(n, timeout):
        source.consumer.consume = consume
        source.consumer.owned = owned
        source._assigned(source.consumer, [TopicPartition("t", p) for p in owned])
        return consume(n, timeout)

    source.consumer.consume = consume_with_a_rebalance


def test_a_batch_polled_while_the_group_changed_is_not_committed() -> None:
    """The assignment callback ran inside consume(): that batch may hold records from
    before it and could never be committed, so it is not handed out; the partitions this
    member still owns are read again from the batch's first offsets (partition 1 went to
    another member), and what comes then is committed."""
    source = _assigned_source([[(0, 900), (1, 40), (0, 901)], [(0, 900), (0, 901)]])
    _rebalancing(source, owned=[0])
    assert source.poll(100, 0.1) == []
    assert source.consumer.seeks == [(0, 900)]
    again = source.poll(100, 0.1)
    assert offsets(again) == [(0, 900), (0, 901)]
    assert source.commit(again) is True
    assert source.consumer.commits == [[(0, 902)]]


@pytest.mark.parametrize("partitions", [[0], [1], [0, 1]])
def test_every_record_delivered_across_a_group_change_is_read_again_until_committed(
    partitions,
) -> None:
    """Whatever partitions a batch polled across a rebalance holds, each record of an owned
    partition comes again in a batch that can be committed: no partition's offset is left
    behind records that were stored (the group would deliver them again on every join)."""
    batch = [(p, o) for o in range(5, 8) for p in partitions]
    source = _assigned_source([batch, batch])
    _rebalancing(source, owned=[0, 1])
    assert source.poll(100, 0.1) == []
    assert sorted(source.consumer.seeks) == [(p, 5) for p in partitions]
    again = source.poll(100, 0.1)
    assert source.commit(again) is True
    assert sorted(source.consumer.commits[0]) == [(p, 8) for p in partitions]


def test_a_batch_that_cannot_be_read_again_is_handed_out_but_not_committed() -> None:
    """A seek librdkafka refuses (the partition not fetching yet): the batch is handed out
    as before, stored, and its offsets are left to a later commit."""
    source = _assigned_source([[(0, 900)], [(0, 2)]])
    source.consumer.seek_fails = True
    _rebalancing(source, owned=[0])
    mixed = source.poll(100, 0.1)
    assert offsets(mixed) == [(0, 900)]
    assert source.commit(mixed) is False and source.consumer.commits == []
    assert source.commit(source.poll(100, 0.1)) is True
    assert source.consumer.commits == [[(0, 3)]]
