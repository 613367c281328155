"""The 2019 wire formats (appendix A of the predecessor's documentation): decode and validate.

Pure functions: bytes in, an `Envelope` or a `Rejection` with a reason code out. Nothing
here raises on bad input, so no message can crash the gateway.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import math
import re
import zlib
from collections.abc import Sequence
from datetime import UTC, datetime
from enum import Enum
from typing import Annotated, Any, TypeVar

import msgspec

from mapservice.core.events import ChunkUpdated, Envelope, MapMetaSet, PoseReported, make_envelope
from mapservice.core.retention import DAY_MS, DEFAULT_RETENTION_MS, older_than_retention

_T = TypeVar("_T")


# Bounds on free-text fields, checked while decoding: a 120 KB "charging" string is a
# wrong_type dead letter, not a row. The 2019 contract sends short words or booleans.
Flag = Annotated[str, msgspec.Meta(max_length=64)]
TimestampText = Annotated[str, msgspec.Meta(max_length=64)]
RobotIdText = Annotated[str, msgspec.Meta(max_length=256)]  # then 1-64 of a charset (below)


class Reason(str, Enum):
    """Why a message went to the dead-letter topic; one code per class of bad input."""

    OVERSIZED = "oversized"
    NOT_JSON = "not_json"
    MISSING_FIELD = "missing_field"
    WRONG_TYPE = "wrong_type"
    BAD_ROBOT_ID = "bad_robot_id"
    BAD_BASE64 = "bad_base64"
    BAD_ZLIB = "bad_zlib"
    WRONG_CHUNK_SIZE = "wrong_chunk_size"
    OUT_OF_MAP = "out_of_map"
    OUT_OF_RANGE = "out_of_range"
    GRID_SHORT_OF_MAP = "grid_short_of_map"  # a map meta whose chunk grid does not cover it
    BAD_TIMESTAMP = "bad_timestamp"
    TIMESTAMP_IN_FUTURE = "timestamp_in_future"
    TIMESTAMP_TOO_OLD = "timestamp_too_old"
    ROBOT_ID_MISMATCH = "robot_id_mismatch"
    UNKNOWN_TOPIC = "unknown_topic"
    TOO_DEEP = "too_deep"  # JSON nested deeper than the decoder goes (msgspec: RecursionError)
    INTERNAL_ERROR = "internal_error"  # anything else that went wrong with this message
    RECORD_TOO_LARGE = "record_too_large"  # accepted, but Kafka refuses a record that large
    TOO_MANY_NEW_ROBOTS = "too_many_new_robots"  # valid, but over the gateway's new-robot limit
    VDA_SCHEMA = "vda_schema"  # not valid against the official VDA 5050 schema of its version
    VDA_UNSUPPORTED_VERSION = "vda_unsupported_version"  # no vendored schema for its version
    VDA_NO_POSITION = "vda_no_position"  # a visualization without a position: nothing to store
    BAD_COMMAND_RESPONSE = "bad_command_response"  # a robot's ack/outcome of no known type or value
    UNKNOWN_COMMAND = "unknown_command"  # an answer to a command the gateway never delivered
    NOT_ITS_COMMAND = "not_its_command"  # an answer to a command sent to another robot


class Rejection(msgspec.Struct, frozen=True):
    reason: Reason
    detail: str


class Limits(msgspec.Struct, frozen=True):
    """What a valid message must respect; the map meta, once known, narrows the grid."""

    chunk_width: int = 100
    chunk_height: int = 100
    chunk_rows: int = 1000
    chunk_cols: int = 1000
    max_message_bytes: int = 256 * 1024
    max_future_skew_ms: int = 300_000
    retention_ms: int = DEFAULT_RETENTION_MS

    def with_meta(self, meta: MapMetaSet) -> Limits:
        return msgspec.structs.replace(
            self,
            chunk_width=meta.chunk_width,
            chunk_height=meta.chunk_height,
            chunk_rows=meta.chunk_rows,
            chunk_cols=meta.chunk_cols,
        )


# --- wire structs (field names as robots send them) -----------------------------------


class ChunkCreate(msgspec.Struct):
    pgmB64compressedData: str
    row: int
    column: int
    timestamp: TimestampText
    robotId: RobotIdText


class Vec3(msgspec.Struct):
    x: float
    y: float
    z: float = 0.0


class Quaternion(msgspec.Struct):
    x: float
    y: float
    z: float
    w: float


class Pose(msgspec.Struct):
    position: Vec3
    orientation: Quaternion


class Battery(msgspec.Struct):
    battery_level: float | None = None
    charging: bool | Flag | None = None


class Status(msgspec.Struct):
    battery: Battery | None = None
    loaded: bool | Flag | None = None


class Point(msgspec.Struct):
    x: float
    y: float


class CoordinateUpdate(msgspec.Struct):
    robotId: RobotIdText
    timestamp: TimestampText
    pose: Pose
    status: Status | None = None
    plannedPath: list[Point] | None = None


_chunk_decoder = msgspec.json.Decoder(ChunkCreate)
_pose_decoder = msgspec.json.Decoder(CoordinateUpdate)
_ROBOT_ID = re.compile(r"[A-Za-z0-9_.:@-]{1,64}")  # fullmatch: `$` would allow "id\n"
MAX_PATH_POINTS = 1000
MAX_ABS_METRES = 1e6


def decode(decoder: msgspec.json.Decoder[_T], data: bytes, what: str = "payload") -> _T | Rejection:
    """`data` decoded into the decoder's type, or the Rejection that says why not
    (`what` names the message in the detail)."""
    try:
        return decoder.decode(data)
    except msgspec.ValidationError as exc:
        text = str(exc)
        reason = Reason.MISSING_FIELD if "missing required field" in text else Reason.WRONG_TYPE
        return Rejection(reason, text)
    except msgspec.DecodeError as exc:
        return Rejection(Reason.NOT_JSON, f"{what} is not JSON: {exc}")
    except UnicodeDecodeError as exc:  # msgspec raises it for invalid UTF-8 inside a string
        return Rejection(Reason.NOT_JSON, f"{what} is not UTF-8 JSON: {exc}")
    except RecursionError:
        # A small message nested ~1,000 levels deep: msgspec gives up; so do we, politely.
        return Rejection(Reason.TOO_DEEP, "JSON nested too deeply to decode")


def oversized(size: int, limits: Limits) -> Rejection:
    return Rejection(Reason.OVERSIZED, f"{size} bytes exceeds the {limits.max_message_bytes} limit")


# Instants a query may name: the Unix epoch to 2262-04-11, the last instant whose
# nanoseconds fit a signed 64-bit integer (MCAP's log times, foxglove's Timestamp,
# numpy's datetime64[ns]); later ones overflow the exports and mean nothing here.
LATEST_INSTANT_MS = 9_223_372_036_854
_EPOCH_MS = re.compile(r"-?[0-9]+")


def parse_query_instant(text: str) -> int | None:
    """A query's instant, ISO 8601 (UTC when no zone is given) or epoch milliseconds;
    None when it is neither or falls outside 1970..2262."""
    if len(text) > 64:  # int() of thousands of digits is slow, then refused
        return None
    # fullmatch, not str.isdigit(): "--5" and "²" would reach int()
    ms = int(text) if _EPOCH_MS.fullmatch(text) else parse_timestamp(text)
    if ms is None or not 0 <= ms <= LATEST_INSTANT_MS:
        return None
    return ms


def parse_timestamp(text: str) -> int | None:
    """ISO 8601 to epoch milliseconds; a timestamp without a zone is UTC (as in 2019)."""
    try:
        parsed = datetime.fromisoformat(text)
    except ValueError:
        return None
    if parsed.tzinfo is None:
        parsed = parsed.replace(tzinfo=UTC)
    return round(parsed.timestamp() * 1000)


_MINUTE_PREFIXES: dict[int, str] = {}  # epoch minute -> "2018-12-20T23:34:"


def format_timestamp(ms: int) -> str:
    """Epoch milliseconds to the 2019 style (`2018-12-20T23:34:33`, `.123` if needed).

    Each minute's date and time prefix is computed once: every live message, API row and
    load-fleet message is formatted here, and datetime took ~2 µs of that per call."""
    if type(ms) is not int:
        return _format_timestamp_datetime(ms)
    minute, rest = divmod(ms, 60_000)
    prefix = _MINUTE_PREFIXES.get(minute)
    if prefix is None:
        if len(_MINUTE_PREFIXES) >= 100_000:
            _MINUTE_PREFIXES.clear()
        prefix = _format_timestamp_datetime(minute * 60_000)[:-2]
        _MINUTE_PREFIXES[minute] = prefix
    second, milli = divmod(rest, 1000)
    return f"{prefix}{second:02d}.{milli:03d}" if milli else f"{prefix}{second:02d}"


def _format_timestamp_datetime(ms: int | float) -> str:
    dt = datetime.fromtimestamp(ms / 1000, tz=UTC).replace(tzinfo=None)
    return dt.isoformat(timespec="milliseconds" if ms % 1000 else "seconds")


def format_timestamps(ms: Sequence[int]) -> list[str]:
    """`format_timestamp` of many at once: ~8x faster (a whole map at T is ~1,500 of them)."""
    import numpy as np  # here: the gateway imports this module and needs no numpy

    if not len(ms):
        return []
    texts = np.datetime_as_string(
        np.asarray(ms, dtype=np.int64).astype("datetime64[ms]"), unit="ms"
    ).tolist()
    return [t.removesuffix(".000") for t in texts]


def _check_time(text: str, now_ms: int, limits: Limits) -> int | Rejection:
    ms = parse_timestamp(text)
    if ms is None:
        return Rejection(Reason.BAD_TIMESTAMP, f"timestamp {text[:64]!r} is not ISO 8601")
    if ms > now_ms + limits.max_future_skew_ms:
        return Rejection(
            Reason.TIMESTAMP_IN_FUTURE,
            f"timestamp {text[:64]} is {(ms - now_ms) / 1000:.1f} s ahead of the gateway clock "
            f"(allowed {limits.max_future_skew_ms / 1000:.0f} s); check the robot's clock",
        )
    if older_than_retention(ms, now_ms, limits.retention_ms):
        return Rejection(
            Reason.TIMESTAMP_TOO_OLD,
            f"timestamp {text[:64]} is older than the {limits.retention_ms // DAY_MS}-day "
            "retention",
        )
    return ms


check_time = _check_time  # the VDA 5050 ingest checks its timestamps the same way


def _check_robot_id(robot_id: str) -> Rejection | None:
    if not _ROBOT_ID.fullmatch(robot_id):
        return Rejection(
            Reason.BAD_ROBOT_ID,
            f"robotId {robot_id[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . : @ -",
        )
    return None


def _mismatch(topic_robot_id: str, payload_robot_id: str) -> Rejection:
    return Rejection(
        Reason.ROBOT_ID_MISMATCH,
        f"topic names robot {topic_robot_id[:80]!r} but the payload says {payload_robot_id!r}",
    )


def decode_chunk_create(
    data: bytes, receive_ms: int, limits: Limits, topic_robot_id: str | None = None
) -> Envelope | Rejection:
    """Validate an `iot/chunks/create` message (listing 14) into a ChunkUpdated event.

    `topic_robot_id` is the robot a per-robot chunk topic (`iot/chunks/create/{robotId}`)
    names; the payload's robotId must be the same. None: the 2019 topic, which names none."""
    if len(data) > limits.max_message_bytes:
        return oversized(len(data), limits)
    msg = decode(_chunk_decoder, data)
    if isinstance(msg, Rejection):
        return msg
    if bad := _check_robot_id(msg.robotId):
        return bad
    if topic_robot_id is not None and msg.robotId != topic_robot_id:
        return _mismatch(topic_robot_id, msg.robotId)
    if not (0 <= msg.row < limits.chunk_rows and 0 <= msg.column < limits.chunk_cols):
        return Rejection(
            Reason.OUT_OF_MAP,
            f"chunk row {msg.row}, column {msg.column} is outside the map of "
            f"{limits.chunk_rows} rows x {limits.chunk_cols} columns",
        )
    event_ms = _check_time(msg.timestamp, receive_ms, limits)
    if isinstance(event_ms, Rejection):
        return event_ms
    try:
        compressed = base64.b64decode(msg.pgmB64compressedData, validate=True)
    except (binascii.Error, ValueError) as exc:
        return Rejection(Reason.BAD_BASE64, f"pgmB64compressedData is not base64: {exc}")
    expected = limits.chunk_width * limits.chunk_height
    try:
        inflater = zlib.decompressobj()
        # Bounded so a zlib bomb costs at most one chunk plus a byte.
        pixels = inflater.decompress(compressed, expected + 1)
        if not inflater.eof and len(pixels) <= expected:
            return Rejection(Reason.BAD_ZLIB, "pgmB64compressedData is a truncated zlib stream")
    except zlib.error as exc:
        return Rejection(Reason.BAD_ZLIB, f"pgmB64compressedData is not zlib data: {exc}")
    if len(pixels) != expected:
        got = f"{len(pixels)}" if len(pixels) <= expected else f"more than {expected}"
        return Rejection(
            Reason.WRONG_CHUNK_SIZE,
            f"chunk decompresses to {got} bytes, expected {limits.chunk_width} x "
            f"{limits.chunk_height} = {expected}",
        )
    payload = ChunkUpdated(
        row=msg.row,
        column=msg.column,
        width=limits.chunk_width,
        height=limits.chunk_height,
        data=compressed,
        content_hash=content_hash(pixels),
    )
    return make_envelope(msg.robotId, event_ms, receive_ms, payload)


def content_hash(pixels: bytes) -> bytes:
    return hashlib.blake2b(pixels, digest_size=16).digest()


def _finite(*values: float | None) -> bool:
    return all(v is None or (math.isfinite(v) and abs(v) < MAX_ABS_METRES) for v in values)


finite = _finite  # the VDA 5050 ingest bounds the numbers it stores the same way


def decode_coordinates(
    topic_robot_id: str, data: bytes, receive_ms: int, limits: Limits
) -> Envelope | Rejection:
    """Validate an `iot/coordinates/{robotId}` message (listing 16) into a PoseReported."""
    if len(data) > limits.max_message_bytes:
        return oversized(len(data), limits)
    msg = decode(_pose_decoder, data)
    if isinstance(msg, Rejection):
        return msg
    if bad := _check_robot_id(msg.robotId):
        return bad
    if msg.robotId != topic_robot_id:
        return _mismatch(topic_robot_id, msg.robotId)
    event_ms = _check_time(msg.timestamp, receive_ms, limits)
    if isinstance(event_ms, Rejection):
        return event_ms
    p, q = msg.pose.position, msg.pose.orientation
    status = msg.status or Status()
    battery = status.battery or Battery()
    path = msg.plannedPath
    if path is not None and len(path) > MAX_PATH_POINTS:
        return Rejection(
            Reason.OUT_OF_RANGE, f"plannedPath has {len(path)} points (at most {MAX_PATH_POINTS})"
        )
    coords = [p.x, p.y, p.z, q.x, q.y, q.z, q.w, battery.battery_level]
    if path:
        coords += [c for pt in path for c in (pt.x, pt.y)]
    if not _finite(*coords):
        return Rejection(
            Reason.OUT_OF_RANGE, f"pose values must be finite and below {MAX_ABS_METRES:g} m"
        )
    payload = PoseReported(
        position=(p.x, p.y, p.z),
        orientation=(q.x, q.y, q.z, q.w),
        battery_level=battery.battery_level,
        charging=battery.charging,
        loaded=status.loaded,
        path=tuple((pt.x, pt.y) for pt in path) if path is not None else None,
    )
    return make_envelope(msg.robotId, event_ms, receive_ms, payload)


def encode_pixels(pixels: bytes) -> str:
    """A chunk's `pgmB64compressedData`: its grey levels, zlib-compressed, in base64."""
    return base64.b64encode(zlib.compress(pixels)).decode()


def encode_chunk_create(
    row: int, column: int, pixels: bytes, timestamp: str, robot_id: str
) -> bytes:
    """A 2019 `iot/chunks/create` message, as a robot would send it."""
    return msgspec.json.encode(
        {
            "pgmB64compressedData": encode_pixels(pixels),
            "row": row,
            "column": column,
            "timestamp": timestamp,
            "robotId": robot_id,
        }
    )


def encode_coordinates(
    robot_id: str,
    timestamp: str,
    x: float,
    y: float,
    yaw_quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
    battery_level: float = 100.0,
    charging: bool | str = False,
    loaded: bool | str = False,
    path: list[tuple[float, float]] | None = None,
) -> bytes:
    """A 2019 `iot/coordinates/{robotId}` message (listing 16), plus the optional path. The
    flags are booleans or, as listing 16 prints them, short free text."""
    qx, qy, qz, qw = yaw_quaternion
    doc: dict[str, Any] = {
        "robotId": robot_id,
        "timestamp": timestamp,
        "pose": {
            "position": {"x": x, "y": y, "z": 0},
            "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
        },
        "status": {
            "battery": {"battery_level": battery_level, "charging": charging},
            "loaded": loaded,
        },
    }
    if path is not None:
        doc["plannedPath"] = [{"x": px, "y": py} for px, py in path]
    return msgspec.json.encode(doc)
