"""The broker-free gateway core: route, publish, and ack only once the log has the record."""

from __future__ import annotations

from functools import partial

import pytest
from mapservice.ingest.gateway import Ingestor

from mapservice.core.events import MapMetaSet, decode, decode_dead_letter
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher


class Acks:
    """Counts ack() calls, the way paho's client.ack(mid, qos) would be called."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def for_(self, name: str):
        return lambda: self.calls.append(name)


@pytest.fixture
def publisher() -> MemoryPublisher:
    return MemoryPublisher()


@pytest.fixture
def settings() -> Settings:
    return Settings()


@pytest.fixture
def ingestor(settings, publisher, clock) -> Ingestor:
    return Ingestor(settings, publisher, clock, gateway_id="gw-test", retry_delay_s=0)


@pytest.fixture
def acks() -> Acks:
    return Acks()


def test_accepted_chunk_is_published_to_chunk_topic(
    ingestor, publisher, settings, wire, acks
) -> None:
    """An accepted chunk lands on the chunk topic with key `row:column`."""
    ingestor.handle("iot/chunks/create", wire.chunk(row=4, column=9), acks.for_("m1"))
    publisher.poll()
    assert list(publisher.records) == [settings.topic_chunk_events]
    ((key, value),) = publisher.records[settings.topic_chunk_events]
    assert key == b"4:9"
    assert decode(value).payload.row == 4


def test_accepted_pose_is_published_to_pose_topic(
    ingestor, publisher, settings, wire, acks, now_ms
) -> None:
    """An accepted pose lands on the pose topic keyed by robot, stamped with the clock's time."""
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("m1"))
    publisher.poll()
    ((key, value),) = publisher.records[settings.topic_pose_events]
    assert key == b"blabla"
    assert decode(value).receive_time_ms == now_ms


def test_rejected_message_goes_to_dead_letter_topic(ingestor, publisher, settings, acks) -> None:
    """A rejected message is published as a dead letter (reason, detail, bytes, topic) and acked."""
    ingestor.handle("iot/chunks/create", b"\x00not json", acks.for_("bad"))
    publisher.poll()
    ((key, value),) = publisher.records[settings.topic_dead_letter]
    letter = decode_dead_letter(value)
    assert key == b"iot/chunks/create"
    assert (letter.reason, letter.payload, letter.mqtt_topic, letter.gateway) == (
        "not_json",
        b"\x00not json",
        "iot/chunks/create",
        "gw-test",
    )
    assert letter.detail
    assert acks.calls == ["bad"]


def test_ack_waits_for_delivery(ingestor, publisher, wire, acks) -> None:
    """ack() is not called when handle() returns, only once the publisher delivered (on poll)."""
    ingestor.handle("iot/chunks/create", wire.chunk(), acks.for_("chunk"))
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("pose"))
    ingestor.handle("iot/chunks/create", b"garbage", acks.for_("bad"))
    assert acks.calls == []
    assert ingestor.in_flight == 3
    assert not publisher.records
    publisher.poll()
    assert acks.calls == ["chunk", "pose", "bad"]
    assert ingestor.in_flight == 0


def test_failed_delivery_is_retried_and_ack_waits(
    ingestor, publisher, settings, wire, acks
) -> None:
    """A failed delivery is published again; ack waits until a delivery succeeds, once."""
    publisher.fail_with = RuntimeError("broker down")
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("pose"))
    publisher.poll()  # fails; the record waits for its retry
    assert ingestor.retries_waiting == 1 and ingestor.retry_due() == 1
    publisher.poll()  # fails again
    assert ingestor.retry_due() == 1
    assert acks.calls == []
    assert ingestor.in_flight == 1
    assert not publisher.records[settings.topic_pose_events]
    publisher.fail_with = None
    publisher.poll()
    assert acks.calls == ["pose"]
    assert ingestor.in_flight == 0
    assert len(publisher.records[settings.topic_pose_events]) == 1
    publisher.poll()
    assert acks.calls == ["pose"]  # acked exactly once


def test_publisher_failing_from_the_start(settings, clock, wire, acks) -> None:
    """MemoryPublisher(fail_with=...) never acks until the failure clears."""
    publisher = MemoryPublisher(fail_with=OSError("no route to broker"))
    ingestor = Ingestor(settings, publisher, clock, "gw", retry_delay_s=0)
    ingestor.handle("iot/chunks/create", wire.chunk(), acks.for_("c"))
    publisher.poll()
    assert acks.calls == []
    publisher.fail_with = None
    assert ingestor.retry_due() == 1
    assert publisher.flush() == 0
    assert acks.calls == ["c"]


def test_a_failed_delivery_waits_its_delay_without_holding_up_other_reports(
    settings, clock, wire, acks
) -> None:
    """A failed record is not produced again inside the delivery callback (which would
    hold up every other report) but by retry_due() once its delay has passed."""
    publisher = MemoryPublisher(fail_with=OSError("request timed out"))
    now = [100.0]
    ingestor = Ingestor(
        settings, publisher, clock, "gw", retry_delay_s=0.2, monotonic=lambda: now[0]
    )
    for n in range(3):
        ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_(f"p{n}"))
    publisher.poll()  # three failures, served at once
    assert ingestor.retries_waiting == 3 and ingestor.retry_due() == 0
    now[0] += 0.2
    publisher.fail_with = None
    assert ingestor.retry_due() == 3
    publisher.poll()
    assert acks.calls == ["p0", "p1", "p2"] and ingestor.in_flight == 0


def test_returned_record_describes_the_outcome(ingestor, wire) -> None:
    """handle() returns the routed record: reason None for events, the code for rejections."""
    assert ingestor.handle("iot/chunks/create", wire.chunk(), lambda: None).reason is None
    assert ingestor.handle("iot/nowhere", wire.chunk(), lambda: None).reason == "unknown_topic"


def test_clock_decides_what_is_too_new(ingestor, clock, wire, acks) -> None:
    """The injected clock is the gateway's now: moving it back makes a message 'in the future'."""
    assert ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None).reason is None
    clock.advance(-3_600_000)
    record = ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None)
    assert record.reason == "timestamp_in_future"


def test_settings_define_the_initial_limits(clock, wire) -> None:
    """Chunk size, grid bound and message size come from the settings until a meta is set."""
    s = Settings(chunk_width=10, chunk_height=10, max_grid=5, max_message_bytes=4096)
    ing = Ingestor(s, MemoryPublisher(), clock, "gw")
    small = wire.chunk(pgmB64compressedData=wire.b64z(bytes(100)), row=4, column=4)
    assert ing.handle("iot/chunks/create", small, lambda: None).reason is None
    assert ing.handle("iot/chunks/create", wire.chunk(), lambda: None).reason == "wrong_chunk_size"
    assert (
        ing.handle(
            "iot/chunks/create",
            wire.chunk(pgmB64compressedData=wire.b64z(bytes(100)), row=5),
            lambda: None,
        ).reason
        == "out_of_map"
    )
    assert ing.handle("iot/chunks/create", b"x" * 5000, lambda: None).reason == "oversized"


def test_apply_meta_narrows_the_grid(ingestor, wire) -> None:
    """After apply_meta, chunks outside the meta's rows/columns are out_of_map."""
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=10, column=10), lambda: None).reason
        is None
    )
    ingestor.apply_meta(
        MapMetaSet(
            width=300, height=200, chunk_width=100, chunk_height=100, chunk_rows=2, chunk_cols=3
        )
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=10, column=10), lambda: None).reason
        == "out_of_map"
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=1, column=2), lambda: None).reason
        is None
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=2, column=0), lambda: None).reason
        == "out_of_map"
    )


def test_apply_meta_sets_chunk_size_and_does_not_compound(ingestor, wire) -> None:
    """apply_meta replaces (not stacks) the previous meta, chunk size included."""
    ingestor.apply_meta(
        MapMetaSet(
            width=100, height=100, chunk_width=50, chunk_height=50, chunk_rows=2, chunk_cols=2
        )
    )
    half = wire.chunk(pgmB64compressedData=wire.b64z(bytes(2500)), row=1, column=1)
    assert ingestor.handle("iot/chunks/create", half, lambda: None).reason is None
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=1, column=1), lambda: None).reason
        == "wrong_chunk_size"
    )
    ingestor.apply_meta(
        MapMetaSet(
            width=800, height=800, chunk_width=100, chunk_height=100, chunk_rows=8, chunk_cols=8
        )
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=7, column=7), lambda: None).reason
        is None
    )
    assert ingestor.limits.max_message_bytes == Settings().max_message_bytes


def test_every_dead_letter_reason_has_a_series_from_the_start() -> None:
    """The rejected counter exists at 0 for each reason before any message is rejected."""
    import mapservice.ingest.metrics  # noqa: F401
    from prometheus_client import REGISTRY

    from mapservice.core.wire2019 import Reason

    for reason in Reason:
        assert (
            REGISTRY.get_sample_value("mapservice_gateway_rejected_total", {"reason": reason.value})
            is not None
        )


def test_the_mqtt_connected_gauge_follows_the_session() -> None:
    """mapservice_gateway_mqtt_connected is 1 after a successful connect and 0 after a disconnect."""
    from mapservice.ingest.gateway import MqttGateway
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.reasoncodes import ReasonCode
    from prometheus_client import REGISTRY

    from mapservice.settings import Settings

    class Client:
        def subscribe(self, topics):
            self.topics = topics

    gateway = MqttGateway(Settings(kafka_bootstrap="127.0.0.1:1"))
    gateway._on_connect(Client(), None, None, ReasonCode(PacketTypes.CONNACK, "Success"), None)
    assert REGISTRY.get_sample_value("mapservice_gateway_mqtt_connected") == 1
    gateway._on_disconnect(
        Client(), None, None, ReasonCode(PacketTypes.DISCONNECT, "Normal disconnection"), None
    )
    assert REGISTRY.get_sample_value("mapservice_gateway_mqtt_connected") == 0


# --- poison messages: none stops the gateway -----------------------------------------------

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
    import mapservice.ingest.router as router

    def broken(*_args, **_kw):
        raise KeyError("surprise")

    monkeypatch.setattr(router, "decode_coordinates", broken)
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


def test_the_mqtt_callback_survives_a_failing_producer(settings, wire) -> None:
    """If even the producer fails, on_message logs and counts it, leaves the message unacked and returns."""
    from mapservice.ingest.gateway import MqttGateway
    from prometheus_client import REGISTRY

    from mapservice.adapters.clock import SystemClock

    gateway = MqttGateway(Settings(kafka_bootstrap="127.0.0.1:1"))
    gateway.ingestor = Ingestor(settings, Broken(), SystemClock(), gateway_id="gw-test")
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


class AckLog:
    """paho's client as the gateway acknowledges through it: each ack_many call's acks."""

    def __init__(self) -> None:
        self.batches: list = []

    def ack_many(self, acks) -> None:
        self.batches.append(list(acks))


def memory_gateway(settings):
    """An MqttGateway producing into memory, its MQTT client an AckLog."""
    from mapservice.ingest.gateway import MqttGateway

    from mapservice.adapters.clock import SystemClock
    from mapservice.testing.memory_publisher import MemoryPublisher

    gateway = MqttGateway(Settings(kafka_bootstrap="127.0.0.1:1"))
    gateway.publisher = MemoryPublisher()
    gateway.ingestor = Ingestor(settings, gateway.publisher, SystemClock(), gateway_id="gw-test")
    gateway.client = AckLog()
    return gateway


def test_the_gateway_acknowledges_what_one_poll_delivered_in_one_batch(settings, wire) -> None:
    """Messages are acknowledged only once Kafka confirmed them, all of one producer poll's
    confirmations in one ack_many call."""
    gateway = memory_gateway(settings)
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


def test_health_is_not_ok_when_the_mqtt_loop_thread_is_dead(settings) -> None:
    """/healthz's status says not ok when paho's network thread has ended, connected or not."""
    import threading

    from mapservice.ingest.gateway import MqttGateway

    gateway = MqttGateway(Settings(kafka_bootstrap="127.0.0.1:1"))
    gateway._connected.set()

    class Client:
        _thread = threading.Thread(target=lambda: None)

    gateway.client = Client()
    Client._thread.start()
    Client._thread.join()
    status = gateway.status()
    assert status["ok"] is False and status["mqtt_loop_alive"] is False


def test_a_handled_and_delivered_message_leaves_nothing_for_the_cyclic_collector(
    ingestor, publisher, wire
) -> None:
    """Routing, publishing, a failed delivery's retry and the ack free every object by
    reference counting: a cycle per message made gc ~12 % of the gateway's CPU.

    The collector counts every unreachable object of the process, also what a thread left
    by an earlier test drops meanwhile; the ingestor's cycles would come back in every
    round (200 messages with a cycle each left ~2,000), such noise does not: the quietest
    of three rounds is asserted."""
    import gc

    def one_round(first_mid: int) -> int:
        acked = []
        gc.collect()
        gc.disable()
        try:
            publisher.fail_with = RuntimeError("broker down")
            for mid in range(first_mid, first_mid + 200):
                ingestor.handle("iot/coordinates/blabla", wire.pose(), partial(acked.append, mid))
            publisher.poll()  # every delivery fails: each record waits for its retry
            publisher.fail_with = None
            assert ingestor.retry_due() == 200
            publisher.poll()
            assert len(acked) == 200 and ingestor.in_flight == 0
            return gc.collect()
        finally:
            gc.enable()

    counts = [one_round(1000 * r) for r in range(3)]
    assert min(counts) < 10, counts


def test_the_in_flight_gauge_reads_the_gateways_count_when_scraped(settings, wire) -> None:
    """mapservice_gateway_in_flight is the ingestor's count of messages Kafka has not confirmed."""
    from mapservice.ingest.gateway import MqttGateway
    from prometheus_client import REGISTRY

    from mapservice.adapters.clock import SystemClock

    gateway = MqttGateway(Settings(kafka_bootstrap="127.0.0.1:1"))
    gateway.publisher = MemoryPublisher()
    gateway.ingestor = Ingestor(settings, gateway.publisher, SystemClock(), gateway_id="gw-test")
    for _mid in (1, 2):
        gateway.ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None)
    assert REGISTRY.get_sample_value("mapservice_gateway_in_flight") == 2
    gateway.publisher.poll()
    assert REGISTRY.get_sample_value("mapservice_gateway_in_flight") == 0


def test_a_topic_that_is_not_utf8_becomes_an_unknown_topic_dead_letter(settings, wire) -> None:
    """paho raises on reading such a topic; the gateway dead-letters the message (acked) and goes on."""
    import paho.mqtt.client as mqtt

    gateway = memory_gateway(settings)
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


def test_new_robot_ids_beyond_the_limit_are_dead_lettered(publisher, clock, wire, acks) -> None:
    """Open mode: three new robot ids a minute pass, a fourth new one is a dead letter
    `too_many_new_robots` whose detail names the setting, and robots already seen still pass."""
    ingestor = Ingestor(
        Settings(ingest_new_robots_limit="3/minute"), publisher, clock, "gw", retry_delay_s=0
    )
    for robot in ("a", "b", "c", "d", "a"):
        ingestor.handle(f"iot/coordinates/{robot}", wire.pose(robotId=robot), acks.for_(robot))
    publisher.poll()
    settings = Settings()
    stored = [decode(v).robot_id for _, v in publisher.records[settings.topic_pose_events]]
    assert stored == ["a", "b", "c", "a"]
    ((_, value),) = publisher.records[settings.topic_dead_letter]
    letter = decode_dead_letter(value)
    assert letter.reason == "too_many_new_robots" and "'d'" in letter.detail
    assert "MAPSERVICE_INGEST_NEW_ROBOTS_LIMIT" in letter.detail
    assert acks.calls == ["a", "b", "c", "d", "a"]  # the refused one is acknowledged too


def test_no_new_robot_limit_when_empty(publisher, clock, wire, acks) -> None:
    ingestor = Ingestor(
        Settings(ingest_new_robots_limit=""), publisher, clock, "gw", retry_delay_s=0
    )
    for n in range(50):
        ingestor.handle(f"iot/coordinates/r{n}", wire.pose(robotId=f"r{n}"), acks.for_("x"))
    publisher.poll()
    assert len(publisher.records[Settings().topic_pose_events]) == 50
