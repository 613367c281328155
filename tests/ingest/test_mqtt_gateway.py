"""The MQTT side of the gateway (MqttGateway): its metrics, its batched acknowledgements,
its health, and what paho hands it that the router never sees."""

from __future__ import annotations

import pytest

from mapservice.ingest.gateway import Ingestor
from mapservice.testing.memory_publisher import MemoryPublisher
from tests.ingest.ingestor_kit import gateway, settings  # noqa: F401  (fixtures)


def test_every_dead_letter_reason_has_a_series_from_the_start() -> None:
    """The rejected counter exists at 0 for each reason before any message is rejected."""
    from prometheus_client import REGISTRY

    import mapservice.ingest.metrics  # noqa: F401
    from mapservice.core.wire2019 import Reason

    for reason in Reason:
        assert (
            REGISTRY.get_sample_value("mapservice_gateway_rejected_total", {"reason": reason.value})
            is not None
        )


def test_the_mqtt_connected_gauge_follows_the_session(gateway) -> None:
    """mapservice_gateway_mqtt_connected is 1 after a successful connect and 0 after a disconnect."""
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.reasoncodes import ReasonCode
    from prometheus_client import REGISTRY

    class Client:
        def subscribe(self, topics):
            self.topics = topics

    gateway._on_connect(Client(), None, None, ReasonCode(PacketTypes.CONNACK, "Success"), None)
    assert REGISTRY.get_sample_value("mapservice_gateway_mqtt_connected") == 1
    gateway._on_disconnect(
        Client(), None, None, ReasonCode(PacketTypes.DISCONNECT, "Normal disconnection"), None
    )
    assert REGISTRY.get_sample_value("mapservice_gateway_mqtt_connected") == 0


# --- poison messages: none stops the gateway -----------------------------------------------
class AckLog:
    """paho's client as the gateway acknowledges through it: each ack_many call's acks."""

    def __init__(self) -> None:
        self.batches: list = []

    def ack_many(self, acks) -> None:
        self.batches.append(list(acks))


def memory_gateway(gateway, settings, clock):
    """The gateway producing into memory, its MQTT client an AckLog; its clock the tests'
    fixed now, which the `wire` payloads' timestamps are built around."""
    from mapservice.testing.memory_publisher import MemoryPublisher

    gateway.publisher = MemoryPublisher()
    gateway.ingestor = Ingestor(settings, gateway.publisher, clock, gateway_id="gw-test")
    gateway.client = AckLog()
    return gateway


def test_the_gateway_acknowledges_what_one_poll_delivered_in_one_batch(
    gateway, settings, wire, clock
) -> None:
    """Messages are acknowledged only once Kafka confirmed them, all of one producer poll's
    confirmations in one ack_many call."""
    gateway = memory_gateway(gateway, settings, clock)
    for mid in (1, 2, 3):
        msg = type(
            "Msg",
            (),
            {"topic": "iot/coordinates/blabla", "payload": wire.pose(), "mid": mid, "qos": 1},
        )
        gateway._on_message(gateway.client, None, msg)
    assert gateway.client.batches == [] and gateway.ingestor.in_flight == 3  # not in Kafka yet
    gateway._poll()
    assert gateway.client.batches == [[(1, 1), (2, 1), (3, 1)]] and gateway.ingestor.in_flight == 0
    gateway._poll()
    assert len(gateway.client.batches) == 1  # nothing new: no empty ack_many


def test_health_is_not_ok_when_the_mqtt_loop_thread_is_dead(gateway, settings) -> None:
    """/healthz's status says not ok when paho's network thread has ended, connected or not."""
    import threading

    gateway._connected.set()

    class Client:
        _thread = threading.Thread(target=lambda: None)

    gateway.client = Client()
    Client._thread.start()
    Client._thread.join()
    status = gateway.status()
    assert status["ok"] is False and status["mqtt_loop_alive"] is False


def test_the_in_flight_gauge_reads_the_gateways_count_when_scraped(
    gateway, settings, wire, clock
) -> None:
    """mapservice_gateway_in_flight is the ingestor's count of messages Kafka has not confirmed."""
    from prometheus_client import REGISTRY

    gateway.publisher = MemoryPublisher()
    gateway.ingestor = Ingestor(settings, gateway.publisher, clock, gateway_id="gw-test")
    for _mid in (1, 2):
        gateway.ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None)
    assert REGISTRY.get_sample_value("mapservice_gateway_in_flight") == 2
    gateway.publisher.poll()
    assert REGISTRY.get_sample_value("mapservice_gateway_in_flight") == 0


def test_a_topic_that_is_not_utf8_becomes_an_unknown_topic_dead_letter(
    gateway, settings, wire, clock
) -> None:
    """paho raises on reading such a topic; the gateway dead-letters the message (acked) and goes on."""
    import paho.mqtt.client as mqtt

    gateway = memory_gateway(gateway, settings, clock)
    bad = mqtt.MQTTMessage(mid=4, topic=b"iot/coordinates/\xff")
    bad.payload, bad.qos = wire.pose(), 1
    good = mqtt.MQTTMessage(mid=5, topic=b"iot/coordinates/blabla")
    good.payload, good.qos = wire.pose(), 1
    gateway._on_message(gateway.client, None, bad)
    gateway._on_message(gateway.client, None, good)
    gateway._poll()
    assert gateway.client.batches == [[(4, 1), (5, 1)]]
    letters = [value for _, value in gateway.publisher.records[settings.topic_dead_letter]]
    assert len(letters) == 1 and b"unknown_topic" in letters[0] and b"not-utf8:" in letters[0]


def test_closing_a_gateway_releases_its_kafka_clients_without_waiting_for_kafka(gateway) -> None:
    """close() purges and closes the gateway's producer (a record to an unreachable broker
    still in it) and lets its readiness check's admin client go: neither goes on dialling."""
    import time

    from confluent_kafka import KafkaException

    results: list = []
    gateway.publisher.publish("t", b"k", b"v", results.append)
    producer = gateway.publisher._producer
    assert producer is not None and len(producer) > 0
    with pytest.raises(KafkaException):
        gateway.kafka_ready.call()  # nothing answers, but its admin client exists now
    assert gateway.kafka_ready.call.func.admin is not None
    started = time.monotonic()
    gateway.close()
    assert time.monotonic() - started < 5  # not the record's message.timeout.ms
    assert isinstance(results[0], KafkaException)  # reported failed: purged, not lost silently
    with pytest.raises(RuntimeError, match="closed"):
        producer.produce("t", b"v")  # the librdkafka handle itself is closed
    assert gateway.kafka_ready.call.func.admin is None
    with pytest.raises(RuntimeError, match="closed"):
        gateway.publisher.publish("t", b"k", b"v", results.append)


def test_the_loop_waits_long_for_delivery_reports_unless_a_retry_is_waiting(
    gateway, settings, wire, clock
) -> None:
    """A quiet gateway's loop waits up to IDLE_POLL_S in the producer's poll (a delivery
    report ends it at once); while a failed record waits for its retry, RETRY_POLL_S."""
    from mapservice.ingest.gateway import IDLE_POLL_S, RETRY_POLL_S

    gateway = memory_gateway(gateway, settings, clock)
    waits: list[float] = []
    serve = gateway.publisher.poll

    def poll(timeout: float = 0.0) -> None:
        waits.append(timeout)
        serve(timeout)

    gateway.publisher.poll = poll
    gateway._poll()
    gateway.ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None)
    gateway.publisher.fail_with = RuntimeError("broker away")
    gateway._poll()  # the delivery fails: the record waits for its retry
    assert gateway.ingestor.retries_waiting == 1
    gateway._poll()
    assert waits == [IDLE_POLL_S, IDLE_POLL_S, RETRY_POLL_S]
    assert RETRY_POLL_S <= 0.05 < 0.5 <= IDLE_POLL_S
