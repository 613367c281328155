"""The raw load fleet's MQTT packets, decoded by amqtt's packet classes, and its reader."""

from __future__ import annotations

import asyncio

import pytest

from mapservice.bench.fleet.mqtt_packets import (
    PacketReader,
    ProtocolError,
    PublishTemplate,
    connect_packet,
    publish_packet,
    varint,
)

amqtt_packets = pytest.importorskip("amqtt.mqtt.publish")


def _decode(cls, data: bytes):
    from amqtt.adapters import BufferReader

    return asyncio.run(cls.from_stream(BufferReader(data)))


def test_varint_matches_the_specification_examples() -> None:
    """MQTT 3.1.1 section 2.2.3: the boundaries of one to four bytes."""
    assert varint(0) == b"\x00" and varint(127) == b"\x7f"
    assert varint(128) == b"\x80\x01" and varint(16_383) == b"\xff\x7f"
    assert varint(16_384) == b"\x80\x80\x01" and varint(268_435_455) == b"\xff\xff\xff\x7f"
    with pytest.raises(ValueError):
        varint(268_435_456)


@pytest.mark.parametrize("size", [0, 100, 126, 127, 300, 20_000])
def test_a_publish_decodes_as_qos_1_with_its_topic_id_and_payload(size: int) -> None:
    """amqtt reads back topic, packet id, QoS 1 and the payload, across remaining-length sizes."""
    from amqtt.mqtt.publish import PublishPacket

    payload = bytes(range(256)) * (size // 256) + b"x" * (size % 256)
    packet = _decode(PublishPacket, publish_packet("iot/coordinates/robot-0001", payload, 4242))
    assert (packet.topic_name, packet.packet_id, packet.qos, packet.data) == (
        "iot/coordinates/robot-0001",
        4242,
        1,
        payload,
    )
    assert not packet.dup_flag and not packet.retain_flag


def test_a_template_fills_the_field_between_prefix_and_suffix() -> None:
    """Two messages of one template differ in the timestamp and packet id only, and
    fields of other lengths get their own (correct) remaining length."""
    from amqtt.mqtt.publish import PublishPacket

    template = PublishTemplate("t/x", b'{"timestamp":"', b'"}')
    for pid, field in ((1, b"2026-11-23T15:00:00.123"), (65535, b"2026-11-23T15:00:01")):
        packet = _decode(PublishPacket, template.packet(pid, field))
        assert (packet.packet_id, packet.data) == (pid, b'{"timestamp":"' + field + b'"}')


def test_connect_decodes_with_client_id_credentials_and_keepalive() -> None:
    """CONNECT, MQTT 3.1.1, as amqtt's broker would read it."""
    from amqtt.mqtt.connect import ConnectPacket

    packet = _decode(
        ConnectPacket, connect_packet("fleet-1", 45, username="robot-7", password="s3cret")
    )
    assert (packet.proto_name, packet.proto_level) == ("MQTT", 4)
    assert packet.clean_session_flag and packet.variable_header.keep_alive == 45
    assert (packet.payload.client_id, packet.payload.username, packet.payload.password) == (
        "fleet-1",
        "robot-7",
        "s3cret",
    )
    anonymous = _decode(ConnectPacket, connect_packet("fleet-2"))
    assert not anonymous.username_flag and not anonymous.password_flag


def test_reader_takes_pubacks_split_anywhere_and_other_packets_between() -> None:
    """PUBACKs come back whole however the stream is cut; CONNACK and PINGRESP are noted."""
    from amqtt.mqtt.connack import ConnackPacket
    from amqtt.mqtt.puback import PubackPacket

    stream = (
        ConnackPacket.build(0, 0).to_bytes()
        + b"".join(PubackPacket.build(i).to_bytes() for i in (1, 2, 300, 65535))
        + b"\xd0\x00"
        + PubackPacket.build(7).to_bytes()
    )
    for cut in range(len(stream) + 1):
        reader = PacketReader()
        acks = reader.feed(stream[:cut]) + reader.feed(stream[cut:])
        assert acks == [1, 2, 300, 65535, 7] and reader.connacked and reader.pingresps == 1
    byte_by_byte = PacketReader()
    assert [a for b in stream for a in byte_by_byte.feed(bytes([b]))] == [1, 2, 300, 65535, 7]


def test_reader_raises_on_a_refused_connection_and_on_packets_a_publisher_never_gets() -> None:
    """A CONNACK with a non-zero code (bad credential) and a PUBLISH to us are errors."""
    with pytest.raises(ProtocolError, match="refused"):
        PacketReader().feed(b"\x20\x02\x00\x05")
    with pytest.raises(ProtocolError, match="unexpected"):
        PacketReader().feed(publish_packet("a", b"b", 1))
