"""Live stream of stored events: the messages, their Kafka records, the API's fan-out.

The processors, once a batch is stored (so queryable), publish its live messages (and,
once stored, the incidents found in it: live_incidents.py) on the
live topic (`MAPSERVICE_TOPIC_LIVE`); every API process reads that topic from its end and
fans the messages out to its WebSocket subscribers (`LiveHub`). One path whether the
processors run in the API's process or elsewhere, and N API replicas each see it all.
Slow subscribers lose their oldest queued messages rather than slowing anyone.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import msgspec

from mapservice.core.events import ChunkUpdated, Envelope, PoseReported, pose_of
from mapservice.core.wire2019 import format_timestamp

# A record holds a batch's messages as one JSON array; batches are cut so that a record
# stays well below Kafka's default 1 MB message limit (a pose with a 1,000-point planned
# path is ~40 kB of JSON).
MAX_RECORD_BYTES = 256 * 1024


class _LivePose(msgspec.Struct):
    """A pose's live message, encoded from a struct (not a dict per event); the UI reads
    these fields (replay-ui/src/lib/live.ts)."""

    type: str
    robotId: str
    ts_ms: int
    timestamp: str
    receive_time_ms: int
    position: Any
    orientation: Any
    battery_level: Any
    charging: Any
    loaded: Any
    path: Any


class _LiveChunk(msgspec.Struct):
    """A chunk write's live message (see _LivePose)."""

    type: str
    robotId: str
    ts_ms: int
    timestamp: str
    receive_time_ms: int
    row: int
    column: int
    content_hash: str


def _live_struct(e: Envelope) -> _LivePose | _LiveChunk | None:
    p = pose_of(e.payload) or e.payload
    if isinstance(p, PoseReported):
        return _LivePose(
            "pose",
            e.robot_id,
            e.event_time_ms,
            format_timestamp(e.event_time_ms),
            e.receive_time_ms,
            p.position,
            p.orientation,
            p.battery_level,
            p.charging,
            p.loaded,
            p.path,
        )
    if isinstance(p, ChunkUpdated):
        return _LiveChunk(
            "chunk",
            e.robot_id,
            e.event_time_ms,
            format_timestamp(e.event_time_ms),
            e.receive_time_ms,
            p.row,
            p.column,
            p.content_hash.hex(),
        )
    return None


_encode = msgspec.json.Encoder().encode


def live_records(events: Iterable[Envelope], max_bytes: int = MAX_RECORD_BYTES) -> list[bytes]:
    """The live topic's records for a stored batch: JSON arrays of its live messages, in
    the batch's order, each at most `max_bytes` unless a single message is larger."""
    return pack_records((_encode(m) for m in map(_live_struct, events) if m is not None), max_bytes)


def pack_records(parts: Iterable[bytes], max_bytes: int = MAX_RECORD_BYTES) -> list[bytes]:
    """Encoded messages as live-topic records: JSON arrays of them, in order, each at most
    `max_bytes` unless a single message is larger."""
    records: list[bytes] = []
    batch: list[bytes] = []
    size = 2
    for part in parts:
        if batch and size + len(part) + 1 > max_bytes:
            records.append(b"[" + b",".join(batch) + b"]")
            batch, size = [], 2
        batch.append(part)
        size += len(part) + 1
    if batch:
        records.append(b"[" + b",".join(batch) + b"]")
    return records


class BadLiveRecord(ValueError):
    """A live-topic record that is not a JSON array of live messages."""


class LiveText(Mapping[str, Any]):
    """One live message as the JSON text it came in: the API sends it on as it is (adding
    `sent_ms`) instead of decoding it into a dict and encoding it again per viewer; read
    as a mapping (tests, tools), it decodes itself on first use."""

    __slots__ = ("_doc", "text")

    def __init__(self, text: str) -> None:
        self.text = text
        self._doc: dict[str, Any] | None = None

    def _decoded(self) -> dict[str, Any]:
        if self._doc is None:
            self._doc = msgspec.json.decode(self.text)
        return self._doc

    def __getitem__(self, key: str) -> Any:
        return self._decoded()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._decoded())

    def __len__(self) -> int:
        return len(self._decoded())

    def with_sent_ms(self, sent_ms: int) -> str:
        """The text with `"sent_ms": sent_ms` added as its last field."""
        return f'{self.text[:-1]},"sent_ms":{sent_ms}}}'


class _Kind(msgspec.Struct):
    type: str


_decode_raw_list = msgspec.json.Decoder(list[msgspec.Raw]).decode
_decode_kind = msgspec.json.Decoder(_Kind).decode


# What the live topic carries: stored poses and chunk writes, and the incidents found in
# them (mapservice/core/live_incidents.py).
LIVE_TYPES = ("pose", "chunk", "incident")


def live_record_texts(value: bytes) -> list[LiveText]:
    """The messages of one live-topic record, each kept as its JSON text (`LiveText`);
    BadLiveRecord if it is not a JSON array of live messages (LIVE_TYPES)."""
    try:
        raws = _decode_raw_list(value)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise BadLiveRecord(f"not a JSON array: {exc}") from exc
    out = []
    for raw in raws:
        try:
            kind = _decode_kind(raw).type
        except (msgspec.DecodeError, msgspec.ValidationError):
            kind = None
        if kind not in LIVE_TYPES:
            raise BadLiveRecord("not a JSON array of pose/chunk/incident messages")
        out.append(LiveText(bytes(raw).decode()))
    return out
