"""KafkaBatchSource's consumer settings (the consumer itself runs in the integration tests)."""

from __future__ import annotations

from mapservice.adapters.kafka_batch_source import KafkaBatchSource, consumer_config
from mapservice.settings import Settings


def test_consumer_commits_by_hand_and_fetches_with_the_configured_short_wait() -> None:
    """Offsets are never auto-committed or auto-stored, and fetch.wait.max.ms comes from
    the settings (default 50 ms: tansu answers an empty fetch only when the wait ends)."""
    conf = consumer_config(Settings(kafka_fetch_wait_ms=40), "history")
    assert conf["enable.auto.commit"] is False and conf["enable.auto.offset.store"] is False
    assert conf["fetch.wait.max.ms"] == 40
    assert consumer_config(Settings(), "history")["fetch.wait.max.ms"] == 50


def test_constructing_the_source_opens_no_consumer() -> None:
    """No network I/O in the constructor: the consumer is created by start()."""
    source = KafkaBatchSource(Settings(kafka_bootstrap="127.0.0.1:1"), ["t"], "g")
    assert source.consumer is None and source.config["group.id"] == "g"


def lag(group: str, topic: str, partition: str) -> float | None:
    from prometheus_client import REGISTRY

    return REGISTRY.get_sample_value("mapservice_consumer_lag_records",
                                     {"group": group, "topic": topic, "partition": partition})


def test_statistics_set_the_lag_of_each_fetched_partition() -> None:
    """A librdkafka statistics report sets the lag per active partition, skipping unknown (-1) lags and partition -1."""
    import json

    from mapservice.adapters.kafka_batch_source import record_lag

    stats = {"topics": {"poses": {"partitions": {
        "0": {"consumer_lag": 42, "fetch_state": "active"},
        "1": {"consumer_lag": -1, "fetch_state": "active"},
        "2": {"consumer_lag": 7, "fetch_state": "none"},
        "-1": {"consumer_lag": 9, "fetch_state": "active"}}}}}
    record_lag("lag-test", json.dumps(stats))
    assert lag("lag-test", "poses", "0") == 42
    assert lag("lag-test", "poses", "1") is None and lag("lag-test", "poses", "2") is None
    assert lag("lag-test", "poses", "-1") is None


def test_assignment_creates_and_revocation_removes_the_lag_series() -> None:
    """An assigned partition reports lag 0 at once; a revoked one stops being reported by this process."""
    from confluent_kafka import TopicPartition

    source = KafkaBatchSource(Settings(), ["t"], "lag-assign")
    assert source.config["statistics.interval.ms"] > 0 and callable(source.config["stats_cb"])
    source._assigned(None, [TopicPartition("t", 3)])
    assert lag("lag-assign", "t", "3") == 0
    source._revoked(None, [TopicPartition("t", 3)])
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
    source.config["on_commit"](KafkaError(KafkaError.REBALANCE_IN_PROGRESS), [TopicPartition("t", 0, 5)])
    assert failures == [1]
