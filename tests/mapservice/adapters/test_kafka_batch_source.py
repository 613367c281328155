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
