"""KafkaLiveRelay's consumer settings (the relay itself runs against tansu in
tests/integration/test_live_relay.py)."""

from __future__ import annotations

from mapservice.adapters.kafka_live_relay import KafkaLiveRelay, live_consumer_config
from mapservice.settings import Settings


def test_every_api_process_reads_under_an_id_of_its_own_and_commits_nothing() -> None:
    """Two relays never share a group id; nothing is committed; a fresh start reads from the end."""
    a, b = live_consumer_config(Settings()), live_consumer_config(Settings(kafka_fetch_wait_ms=40))
    assert a["group.id"] != b["group.id"] and a["group.id"].startswith("mapservice-api-live-")
    assert a["enable.auto.commit"] is False and a["auto.offset.reset"] == "latest"
    assert b["fetch.wait.max.ms"] == 40


def test_constructing_the_relay_starts_nothing() -> None:
    """No thread and no consumer until start(); not ready before it reads the topic."""
    relay = KafkaLiveRelay(Settings(kafka_bootstrap="127.0.0.1:1", topic_live="t"), lambda _m: None)
    assert relay._thread is None and not relay.assigned.is_set() and relay.topic == "t"
