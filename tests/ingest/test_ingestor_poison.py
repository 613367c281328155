"""Poison messages: none stops the gateway. Each becomes a dead letter naming its reason,
and is acknowledged."""

from __future__ import annotations

from mapservice.core.events import decode_dead_letter
from mapservice.ingest.gateway import Ingestor
from mapservice.testing.memory_publisher import MemoryPublisher
from tests.ingest.ingestor_kit import (  # noqa: F401  (fixtures)
    acks,
    gateway,
    ingestor,
    publisher,
    settings,
)

DEEP = b'{"x":' + b"[" * 1000 + b"]" * 1000 + b"}"


def dead_letters(publisher, settings) -> list:
    publisher.poll()
    return [
        decode_dead_letter(v) for _k, v in publisher.records.get(settings.topic_dead_letter, [])
    ]


def test_a_deeply_nested_message_is_a_dead_letter_and_acknowledged(
    ingestor, publisher, settings, acks
) -> None:
    """A 2 KB JSON nested 1,000 deep becomes a too_deep dead letter; the message is acked."""
    ingestor.handle("iot/coordinates/r1", DEEP, acks.for_("deep"))
    (letter,) = dead_letters(publisher, settings)
    assert letter.reason == "too_deep" and letter.payload == DEEP
    assert acks.calls == ["deep"] and ingestor.in_flight == 0


def test_a_huge_message_leaves_a_dead_letter_that_fits_in_kafka(
    ingestor, publisher, settings, acks
) -> None:
    """A 1.2 MB message: an oversized dead letter holding its first 64 KB, its size and its sha256."""
    import hashlib

    payload = b'{"robotId": "r1", "x": "' + b"a" * 1_200_000 + b'"}'
    ingestor.handle("iot/coordinates/r1", payload, acks.for_("huge"))
    publisher.poll()
    ((_key, value),) = publisher.records[settings.topic_dead_letter]
    assert len(value) < 100_000
    letter = decode_dead_letter(value)
    assert letter.reason == "oversized" and letter.payload == payload[: 64 * 1024]
    assert (
        str(len(payload)) in letter.detail and hashlib.sha256(payload).hexdigest() in letter.detail
    )
    assert acks.calls == ["huge"]


def test_any_exception_while_routing_becomes_an_internal_error_dead_letter(
    ingestor, publisher, settings, acks, monkeypatch
) -> None:
    """Whatever breaks inside decoding ends as an internal_error dead letter naming it, and an ack."""
    from mapservice.core.intake import Intake

    def broken(*_args, **_kw):
        raise KeyError("surprise")

    monkeypatch.setattr(Intake, "coordinates", broken)
    ingestor.handle("iot/coordinates/r1", b"{}", acks.for_("m"))
    (letter,) = dead_letters(publisher, settings)
    assert letter.reason == "internal_error" and "KeyError" in letter.detail
    assert acks.calls == ["m"]


class TooLargeForKafka(MemoryPublisher):
    """Refuses records on `topic`, as librdkafka does a record over message.max.bytes."""

    def __init__(self, topic: str) -> None:
        super().__init__()
        self.topic = topic

    def publish(self, topic, key, value, on_done) -> None:
        from mapservice.adapters.kafka_publisher import RecordTooLarge

        if topic == self.topic:
            raise RecordTooLarge(f"{len(value)} bytes: larger than Kafka takes")
        super().publish(topic, key, value, on_done)


def test_a_record_kafka_refuses_becomes_a_record_too_large_dead_letter(
    settings, clock, wire, acks
) -> None:
    """An accepted message whose record Kafka refuses as too large is dead-lettered and acked."""
    publisher = TooLargeForKafka(settings.topic_pose_events)
    ingestor = Ingestor(settings, publisher, clock, gateway_id="gw-test")
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("big"))
    publisher.poll()
    assert not publisher.records.get(settings.topic_pose_events)
    (letter,) = [decode_dead_letter(v) for _k, v in publisher.records[settings.topic_dead_letter]]
    assert letter.reason == "record_too_large" and "larger than Kafka takes" in letter.detail
    assert acks.calls == ["big"] and ingestor.in_flight == 0


class Broken(MemoryPublisher):
    def publish(self, topic, key, value, on_done) -> None:
        raise RuntimeError("producer gone")


def test_the_mqtt_callback_survives_a_failing_producer(gateway, settings, wire, clock) -> None:
    """If even the producer fails, on_message logs and counts it, leaves the message unacked and returns."""
    from prometheus_client import REGISTRY

    gateway.ingestor = Ingestor(settings, Broken(), clock, gateway_id="gw-test")
    before = REGISTRY.get_sample_value("mapservice_gateway_handling_errors_total") or 0

    class Msg:
        topic, payload, mid, qos = "iot/coordinates/blabla", wire.pose(), 7, 1

    class Client:
        acked: list = []

        def ack(self, mid, qos):
            self.acked.append(mid)

    client = Client()
    gateway._on_message(client, None, Msg())
    assert client.acked == [] and not gateway._acks and gateway.ingestor.in_flight == 0
    assert REGISTRY.get_sample_value("mapservice_gateway_handling_errors_total") == before + 1
