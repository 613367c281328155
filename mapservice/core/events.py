"""Frozen, versioned event envelopes and their payloads.

An event's id is derived from what identifies it in the domain, never drawn at random:
a QoS 1 redelivery of the same MQTT message must yield the same id so the history can
drop it, and the history stores the identifying columns (robot, event time, chunk)
instead of a 16-byte id per row.
"""

from __future__ import annotations

import hashlib
from typing import Any

import msgspec

from mapservice.core.annotations import (
    ANNOTATION_EVENTS,
    AnnotationChanged,
    AnnotationCreated,
    AnnotationRemoved,
)
from mapservice.core.commands import (
    COMMAND_EVENTS,
    CommandAcknowledged,
    CommandFinished,
    CommandIssued,
)

SCHEMA_VERSION = 1

# Every record below is frozen and holds only immutable values, so it cannot be part of a
# reference cycle: `gc=False` keeps the many alive at once out of the cyclic collector's
# full collections (mapservice/runtime/heap.py says what those cost).


class ChunkUpdated(msgspec.Struct, frozen=True, gc=False, tag="chunk.updated", array_like=True):
    """A robot wrote one chunk of the shared map."""

    row: int
    column: int
    width: int
    height: int
    data: bytes  # zlib-deflated 8-bit pixels, exactly as the robot sent them
    content_hash: bytes  # blake2b-128 of the decompressed pixels


class PoseReported(msgspec.Struct, frozen=True, gc=False, tag="pose.reported", array_like=True):
    """A robot's pose and status at one instant (positions in metres)."""

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]  # quaternion x, y, z, w
    battery_level: float | None = None
    # The 2019 contract leaves these untyped (booleans or strings); kept as sent.
    charging: bool | str | None = None
    loaded: bool | str | None = None
    path: tuple[tuple[float, float], ...] | None = None


class MapMetaSet(msgspec.Struct, frozen=True, gc=False, tag="map.meta_set", array_like=True):
    """The map's geometry: the 2019 meta.json plus ROS `resolution` and `origin`."""

    width: int
    height: int
    chunk_width: int
    chunk_height: int
    chunk_rows: int
    chunk_cols: int
    comment: str = ""
    max_brightness: str = "255"
    resolution: float | None = None
    origin: tuple[float, float, float] | None = None

    def to_2019(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "comment": self.comment,
            "width": self.width,
            "height": self.height,
            "max_brightness": self.max_brightness,
            "CHUNK_WIDTH": self.chunk_width,
            "CHUNK_HEIGHT": self.chunk_height,
            "CHUNK_ROWS": self.chunk_rows,
            "CHUNK_COLS": self.chunk_cols,
        }
        if self.resolution is not None:
            doc["resolution"] = self.resolution
        if self.origin is not None:
            doc["origin"] = list(self.origin)
        return doc

    @classmethod
    def from_2019(cls, doc: dict[str, Any]) -> MapMetaSet:
        origin = doc.get("origin")
        return cls(
            width=int(doc["width"]),
            height=int(doc["height"]),
            chunk_width=int(doc["CHUNK_WIDTH"]),
            chunk_height=int(doc["CHUNK_HEIGHT"]),
            chunk_rows=int(doc["CHUNK_ROWS"]),
            chunk_cols=int(doc["CHUNK_COLS"]),
            comment=str(doc.get("comment", "")),
            max_brightness=str(doc.get("max_brightness", "255")),
            resolution=float(doc["resolution"]) if doc.get("resolution") is not None else None,
            origin=_origin(origin) if origin is not None else None,
        )


def _origin(values: list[float]) -> tuple[float, float, float]:
    """A ROS map origin [x, y, yaw]; anything but three numbers is a ValueError."""
    x, y, yaw = (float(v) for v in values)
    return (x, y, yaw)


class VdaError(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """One active error or warning a VDA 5050 vehicle reports in its `state`."""

    level: str  # WARNING or FATAL (3.0 adds URGENT, CRITICAL)
    type: str
    description: str = ""


class VdaStateReported(msgspec.Struct, frozen=True, gc=False, tag="vda.state", array_like=True):
    """A VDA 5050 `state` (or a `visualization` off the known maps): what the vehicle
    reported beyond a pose. `pose` is in the map's frame and set only when the vehicle is
    localized on a map id the service has a transform for; x, y, theta are as reported,
    in the vehicle's `map_id` frame, so a vehicle on an unknown map is kept, flagged."""

    manufacturer: str
    serial_number: str
    vda_version: str
    pose: PoseReported | None
    map_id: str | None
    on_known_map: bool
    x: float | None
    y: float | None
    theta: float | None
    driving: bool | None
    paused: bool | None
    operating_mode: str
    order_id: str
    errors: tuple[VdaError, ...] = ()


class VdaConnectionReported(
    msgspec.Struct, frozen=True, gc=False, tag="vda.connection", array_like=True
):
    """A vehicle's `connection` state: ONLINE, OFFLINE or CONNECTIONBROKEN. The event
    time of a CONNECTIONBROKEN is when the broker published the last will (its `timestamp`
    is the connect time, kept in sent_time_ms)."""

    manufacturer: str
    serial_number: str
    vda_version: str
    state: str
    sent_time_ms: int


class VdaFactsheetReported(
    msgspec.Struct, frozen=True, gc=False, tag="vda.factsheet", array_like=True
):
    """A vehicle's `factsheet`, as the JSON it sent (schema-validated)."""

    manufacturer: str
    serial_number: str
    vda_version: str
    factsheet_json: str


Payload = (
    ChunkUpdated
    | PoseReported
    | MapMetaSet
    | VdaStateReported
    | VdaConnectionReported
    | VdaFactsheetReported
    | AnnotationCreated
    | AnnotationChanged
    | AnnotationRemoved
    | CommandIssued
    | CommandAcknowledged
    | CommandFinished
)


def pose_of(payload: Payload) -> PoseReported | None:
    """The drawable pose an event carries: a PoseReported, or a VDA state's pose."""
    if isinstance(payload, PoseReported):
        return payload
    if isinstance(payload, VdaStateReported):
        return payload.pose
    return None


class Envelope(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """What travels on Kafka: an immutable event with its identity and two clocks."""

    event_id: str
    type: str
    version: int
    robot_id: str
    event_time_ms: int  # the robot's timestamp
    receive_time_ms: int  # the gateway's clock
    payload: Payload


def _digest(*parts: object) -> str:
    """blake2b-128 of the parts, each followed by a unit separator (text as UTF-8), hashed
    in one call: a simulated week digests a million ids, and an update per part and per
    separator was most of the cost."""
    data = b"".join(
        (part if isinstance(part, bytes) else str(part).encode()) + b"\x1f" for part in parts
    )
    return hashlib.blake2b(data, digest_size=16).hexdigest()


def event_id_for(robot_id: str, event_time_ms: int, payload: Payload) -> str:
    """The natural identity of an event, as a hex digest.

    A pose is identified by (robot, event time) and a chunk write by (chunk, robot,
    event time), matching the 2019 ids `robotId:<id>_<ts>` and `row:<r>_column:<c>_<ts>`
    (with the robot added so two robots writing one chunk in one second stay apart).
    """
    if isinstance(payload, PoseReported):
        return _digest("pose", robot_id, event_time_ms)
    if isinstance(payload, ChunkUpdated):
        return _digest("chunk", payload.row, payload.column, robot_id, event_time_ms)
    if isinstance(payload, VdaStateReported):
        return _digest("vda.state", robot_id, event_time_ms)
    if isinstance(payload, ANNOTATION_EVENTS):
        # An operator's edit: the annotation, the instant and the whole content (two
        # different edits of one annotation in one millisecond both stay).
        return _digest(
            "annotation", payload.annotation_id, event_time_ms, msgspec.msgpack.encode(payload)
        )
    if isinstance(payload, CommandIssued):
        return _digest("command", payload.command_id)  # issued once, whatever re-sends it
    if isinstance(payload, COMMAND_EVENTS):
        # A robot's answer, by its own time: a QoS 1 redelivery is the same event.
        return _digest(
            "command", payload.command_id, type_of(payload), payload.robot_id, event_time_ms
        )
    return _digest("meta", robot_id, event_time_ms, msgspec.msgpack.encode(payload))


def type_of(payload: Payload) -> str:
    return type(payload).__struct_config__.tag  # type: ignore[return-value]


def make_envelope(
    robot_id: str, event_time_ms: int, receive_time_ms: int, payload: Payload
) -> Envelope:
    return Envelope(
        event_id=event_id_for(robot_id, event_time_ms, payload),
        type=type_of(payload),
        version=SCHEMA_VERSION,
        robot_id=robot_id,
        event_time_ms=event_time_ms,
        receive_time_ms=receive_time_ms,
        payload=payload,
    )


def kafka_key(envelope: Envelope) -> bytes:
    """Chunk events are keyed by `row:column`, poses and commands by robot id, annotation
    edits by the annotation (its topic is compacted: the latest edit of each stays), so
    order per key holds."""
    payload = envelope.payload
    if isinstance(payload, ChunkUpdated):
        return f"{payload.row}:{payload.column}".encode()
    if isinstance(payload, MapMetaSet):
        return b"map"
    if isinstance(payload, ANNOTATION_EVENTS):
        return f"annotation:{payload.annotation_id}".encode()
    return envelope.robot_id.encode()


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(Envelope)


def encode(envelope: Envelope) -> bytes:
    return _encoder.encode(envelope)


def decode(data: bytes) -> Envelope:
    return _decoder.decode(data)


class DeadLetter(msgspec.Struct, frozen=True, gc=False):
    """A rejected MQTT message: the original bytes, where it came from and why."""

    reason: str
    detail: str
    mqtt_topic: str
    payload: bytes
    receive_time_ms: int
    gateway: str
    version: int = SCHEMA_VERSION


_dl_decoder = msgspec.msgpack.Decoder(DeadLetter)


def encode_dead_letter(record: DeadLetter) -> bytes:
    return _encoder.encode(record)


def decode_dead_letter(data: bytes) -> DeadLetter:
    return _dl_decoder.decode(data)
