"""MQTT 3.1.1 packets as bytes, for a load generator that writes them on raw sockets.

paho builds every PUBLISH in Python (~300 µs of CPU per message in `bench ingest`, more
than half a core at 4,000 robots). A robot's messages differ only in their timestamp and
the packet id, so `PublishTemplate` encodes a message once and patches those per message.
Only what a QoS 1 publisher needs: CONNECT, PUBLISH (QoS 1), PINGREQ, DISCONNECT out;
CONNACK, PUBACK, PINGRESP in (`PacketReader`). Tested against amqtt's packet decoder and
through Mosquitto to a paho subscriber (tests/mapservice/bench/test_mqtt_packets.py).
"""

from __future__ import annotations

import struct

CONNECT, CONNACK, PUBLISH, PUBACK, PINGREQ, PINGRESP, DISCONNECT = 1, 2, 3, 4, 12, 13, 14
PINGREQ_PACKET = b"\xc0\x00"
DISCONNECT_PACKET = b"\xe0\x00"
MAX_REMAINING_LENGTH = 268_435_455  # four bytes of variable-length integer


def varint(n: int) -> bytes:
    """MQTT's "remaining length": 7 bits a byte, least significant first."""
    if not 0 <= n <= MAX_REMAINING_LENGTH:
        raise ValueError(f"remaining length {n} out of MQTT's range")
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _string(text: str | bytes) -> bytes:
    data = text.encode() if isinstance(text, str) else text
    if len(data) > 0xFFFF:
        raise ValueError("an MQTT string is at most 65,535 bytes")
    return struct.pack(">H", len(data)) + data


def connect_packet(
    client_id: str,
    keepalive_s: int = 60,
    clean_session: bool = True,
    username: str | None = None,
    password: str | None = None,
) -> bytes:
    """CONNECT, protocol level 4 (MQTT 3.1.1)."""
    flags = (
        (0x02 if clean_session else 0)
        | (0x80 if username is not None else 0)
        | (0x40 if password is not None else 0)
    )
    body = _string("MQTT") + bytes([4, flags]) + struct.pack(">H", keepalive_s) + _string(client_id)
    if username is not None:
        body += _string(username)
    if password is not None:
        body += _string(password)
    return bytes([CONNECT << 4]) + varint(len(body)) + body


def publish_packet(topic: str, payload: bytes, packet_id: int) -> bytes:
    """One QoS 1 PUBLISH (not a duplicate, not retained)."""
    return PublishTemplate(topic, payload, b"").packet(packet_id, b"")


class PublishTemplate:
    """QoS 1 PUBLISHes of `prefix + field + suffix` on one topic, the field (a timestamp)
    filled per message: the topic, payload and header are encoded once."""

    __slots__ = ("_headers", "_topic", "prefix", "suffix")

    def __init__(self, topic: str, prefix: bytes, suffix: bytes) -> None:
        self._topic = _string(topic)
        self.prefix, self.suffix = prefix, suffix
        self._headers: dict[int, bytes] = {}  # field length -> fixed header + topic

    def packet(self, packet_id: int, field: bytes) -> bytes:
        header = self._headers.get(len(field))
        if header is None:
            remaining = len(self._topic) + 2 + len(self.prefix) + len(field) + len(self.suffix)
            header = self._headers[len(field)] = (
                bytes([PUBLISH << 4 | 0x02]) + varint(remaining) + self._topic
            )
        return b"".join((header, packet_id.to_bytes(2, "big"), self.prefix, field, self.suffix))


class ProtocolError(ValueError):
    """The broker sent something a QoS 1 publisher does not expect."""


class PacketReader:
    """Splits the broker's byte stream into packets. `feed(data)` returns the packet ids
    of the PUBACKs in it and counts the rest; a refused CONNACK raises."""

    def __init__(self) -> None:
        self._buffer = b""
        self.connacked = False
        self.pingresps = 0

    def feed(self, data: bytes) -> list[int]:
        buf = self._buffer + data if self._buffer else data
        acks: list[int] = []
        pos, end = 0, len(buf)
        while pos < end:
            first = buf[pos]
            if first == 0x40 and pos + 4 <= end and buf[pos + 1] == 2:  # the common case
                acks.append((buf[pos + 2] << 8) | buf[pos + 3])
                pos += 4
                continue
            # The general case: fixed header, remaining length, body.
            length, shift, i = 0, 0, pos + 1
            while True:
                if i >= end:
                    self._buffer = buf[pos:]
                    return acks
                byte = buf[i]
                length |= (byte & 0x7F) << shift
                i += 1
                if not byte & 0x80:
                    break
                shift += 7
                if shift > 21:
                    raise ProtocolError("remaining length longer than four bytes")
            if i + length > end:
                break
            body = buf[i : i + length]
            kind = first >> 4
            if kind == PUBACK and length == 2:
                acks.append((body[0] << 8) | body[1])
            elif kind == CONNACK and length == 2:
                if body[1] != 0:
                    raise ProtocolError(
                        f"the broker refused the connection (CONNACK code {body[1]})"
                    )
                self.connacked = True
            elif kind == PINGRESP:
                self.pingresps += 1
            else:
                raise ProtocolError(f"unexpected MQTT packet type {kind} from the broker")
            pos = i + length
        self._buffer = buf[pos:] if pos < end else b""
        return acks
