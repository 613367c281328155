"""The gateway's Kafka readers over a stand-in consumer: each assigns every partition of
its topic from where it reads (the meta topic from the beginning, the command topic from
COMMAND_MEMORY_S back, its end where nothing is that recent), hands each record on (a
tombstone or a foreign record skipped), and ends its thread when stopped."""

from __future__ import annotations

import time
from types import SimpleNamespace

import pytest
from confluent_kafka import OFFSET_BEGINNING, OFFSET_END, TopicPartition
from structlog.testing import capture_logs

import mapservice.ingest.topic_follower as topic_follower
from mapservice.core.commands import CommandIssued
from mapservice.core.events import encode, make_envelope
from mapservice.ingest.command_relay import COMMAND_MEMORY_S, CommandRelay
from mapservice.ingest.meta_watcher import MetaWatcher
from mapservice.settings import Settings
from tests.conftest import meta_event
from tests.ingest.gateway_kit import NOW


class Record:
    def __init__(self, value: bytes | None) -> None:
        self._value = value

    def value(self) -> bytes | None:
        return self._value

    def error(self) -> None:
        return None


class StandInConsumer:
    """A topic of two partitions holding `records`; offsets_for_times finds a record of
    partition 0 at offset 7 and none in partition 1."""

    made: list[StandInConsumer] = []
    records: list[bytes | None] = []

    def __init__(self, config: dict) -> None:
        self.config, self.assigned, self.closed = config, [], False
        self.queue = list(self.records)
        self.made.append(self)

    def list_topics(self, topic: str, timeout: float):
        return SimpleNamespace(topics={topic: SimpleNamespace(partitions={0: None, 1: None})})

    def offsets_for_times(self, partitions: list[TopicPartition], timeout: float):
        self.asked_since = {tp.offset for tp in partitions}
        return [
            TopicPartition(tp.topic, tp.partition, 7 if tp.partition == 0 else -1)
            for tp in partitions
        ]

    def assign(self, partitions: list[TopicPartition]) -> None:
        self.assigned = [(tp.topic, tp.partition, tp.offset) for tp in partitions]

    def poll(self, timeout: float) -> Record | None:
        if self.queue:
            return Record(self.queue.pop(0))
        time.sleep(0.01)
        return None

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def consumer(monkeypatch) -> type[StandInConsumer]:
    monkeypatch.setattr(topic_follower, "Consumer", StandInConsumer)
    monkeypatch.setattr(StandInConsumer, "made", [])
    return StandInConsumer


def run_until(follower, done) -> None:
    follower.start()
    deadline = time.monotonic() + 10
    while not done() and time.monotonic() < deadline:
        time.sleep(0.01)
    follower.stop()
    assert follower._thread is not None and not follower._thread.is_alive()


def test_the_meta_watcher_reads_from_the_beginning_and_applies_the_newest_meta(consumer) -> None:
    settings = Settings()
    newer, older = meta_event(NOW, chunk_rows=6), meta_event(NOW - 1000, chunk_rows=3)
    consumer.records = [b"\xc1 foreign", None, encode(newer), encode(older)]
    applied: list = []
    watcher = MetaWatcher(settings, applied.append)
    with capture_logs() as logs:
        run_until(watcher, lambda: consumer.made and not consumer.made[0].queue)
    assert [e["event"] for e in logs if e["log_level"] == "warning"] == [
        "meta record undecodable"
    ] * 2  # the foreign record and the tombstone
    (made,) = consumer.made
    topic = settings.topic_meta_events
    assert made.assigned == [(topic, 0, OFFSET_BEGINNING), (topic, 1, OFFSET_BEGINNING)]
    assert made.config["group.id"] == "mapservice-meta-watcher" and made.closed
    assert [m.chunk_rows for m in applied] == [6] and watcher.newest_ms == NOW


def test_the_command_relay_reads_the_recent_commands_and_skips_tombstones(consumer) -> None:
    settings = Settings()
    command = CommandIssued("c-1", "agv-1", "pause", "operator:ab12", NOW)
    consumer.records = [None, b"\x00garbage", encode(make_envelope("agv-1", NOW, NOW, command))]
    sent: list = []
    relay = CommandRelay(settings, lambda topic, payload: sent.append(topic), lambda: NOW)
    with capture_logs() as logs:
        run_until(relay, lambda: bool(sent))
    # The tombstone is passed over; the garbage is refused by the relay, not a failure.
    assert [e["event"] for e in logs if e["log_level"] in ("warning", "error")] == [
        "command record undecodable; skipped"
    ]
    (made,) = consumer.made
    topic = settings.topic_command_events
    assert made.asked_since == {NOW - COMMAND_MEMORY_S * 1000}
    assert made.assigned == [(topic, 0, 7), (topic, 1, OFFSET_END)] and made.closed
    assert sent == ["iot/robots/agv-1/commands"] and relay.failures == 0
