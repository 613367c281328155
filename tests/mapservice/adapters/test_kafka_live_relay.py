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


def test_the_relay_starts_at_offsets_the_broker_reported_before_it_says_assigned(
    monkeypatch,
) -> None:
    """Each partition starts at the end the broker reported (not OFFSET_END, resolved later), and `assigned` comes after that answer."""
    import threading
    from types import SimpleNamespace

    from mapservice.adapters import kafka_live_relay

    calls: list = []
    relay: KafkaLiveRelay

    class FakeConsumer:
        def __init__(self, _config) -> None:
            pass

        def list_topics(self, topic, timeout):
            return SimpleNamespace(
                topics={topic: SimpleNamespace(error=None, partitions={0: None, 1: None})}
            )

        def get_watermark_offsets(self, tp, timeout, cached):
            calls.append(("watermark", tp.partition, relay.assigned.is_set()))
            return 0, 40 + tp.partition

        def assign(self, tps) -> None:
            calls.append(("assign", [(tp.partition, tp.offset) for tp in tps]))

        def poll(self, timeout):
            relay._stopping.set()
            return None

        def close(self) -> None:
            pass

    monkeypatch.setattr(kafka_live_relay, "Consumer", FakeConsumer)
    relay = KafkaLiveRelay(Settings(kafka_bootstrap="127.0.0.1:1", topic_live="t"), lambda _m: None)
    thread = threading.Thread(target=relay._follow)
    thread.start()
    thread.join(10)
    assert calls == [
        ("watermark", 0, False),
        ("watermark", 1, False),
        ("assign", [(0, 40), (1, 41)]),
    ]
    assert relay.assigned.is_set()
