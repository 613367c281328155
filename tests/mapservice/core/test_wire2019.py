"""The 2019 wire contract (appendix A, listings 14 and 16): decoding and every rejection."""

from __future__ import annotations

import base64
import json
import math
import tracemalloc
import zlib
from dataclasses import dataclass
from datetime import timedelta, timezone
from collections.abc import Callable

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.events import ChunkUpdated, Envelope, MapMetaSet, PoseReported, event_id_for
from mapservice.core.wire2019 import (
    MAX_PATH_POINTS,
    Limits,
    Reason,
    Rejection,
    content_hash,
    decode_chunk_create,
    decode_coordinates,
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
    format_timestamps,
    parse_timestamp,
)

NOW = 1_795_255_200_000  # same instant as conftest.NOW_MS: 2026-11-21T10:00:00Z
DAY = 86_400_000
SKEW = Limits().max_future_skew_ms
RETENTION = Limits().retention_ms


def _b64z(raw: bytes) -> str:
    return base64.b64encode(zlib.compress(raw)).decode()


def _ts(offset_ms: int = 0) -> str:
    return format_timestamp(NOW + offset_ms)


def _chunk(**overrides) -> bytes:
    doc = {"pgmB64compressedData": _b64z(bytes(10_000)), "row": 3, "column": 2,
           "timestamp": _ts(), "robotId": "lkjlkj"}
    doc.update(overrides)
    return json.dumps({k: v for k, v in doc.items() if v is not _DROP}).encode()


def _pose(**overrides) -> bytes:
    doc = {"robotId": "blabla", "timestamp": _ts(),
           "pose": {"position": {"x": 10, "y": 20, "z": 0},
                    "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
           "status": {"battery": {"battery_level": 3, "charging": "sdf"}, "loaded": "dfs"}}
    doc.update(overrides)
    return json.dumps({k: v for k, v in doc.items() if v is not _DROP}).encode()


def _at(x=10, y=20, z=0, q=(0, 0, 0, 1)) -> dict:
    return {"position": {"x": x, "y": y, "z": z},
            "orientation": dict(zip("xyzw", q))}


_DROP = object()
META_4x5 = MapMetaSet(width=500, height=400, chunk_width=100, chunk_height=100,
                      chunk_rows=4, chunk_cols=5)


# --- one concrete bad message per reason code -----------------------------------------


@dataclass(frozen=True)
class Bad:
    id: str
    reason: Reason
    decode: Callable[[], Envelope | Rejection]


def chunk_case(id_: str, reason: Reason, data: bytes, limits: Limits = Limits()) -> Bad:
    return Bad(id_, reason, lambda: decode_chunk_create(data, NOW, limits))


def pose_case(id_: str, reason: Reason, data: bytes, topic_robot: str = "blabla",
              limits: Limits = Limits()) -> Bad:
    return Bad(id_, reason, lambda: decode_coordinates(topic_robot, data, NOW, limits))


_pixels = bytes(range(256)) * 39 + bytes(16)  # exactly 10_000 bytes
_full = zlib.compress(_pixels)
_bad_check = _full[:-1] + bytes([_full[-1] ^ 0xFF])

BAD_CASES = [
    # not_json
    chunk_case("chunk-not-json", Reason.NOT_JSON, b'{"row": 3,'),
    chunk_case("chunk-empty-body", Reason.NOT_JSON, b""),
    pose_case("pose-binary-garbage", Reason.NOT_JSON, b"\xff\xfe\x00garbage"),
    pose_case("pose-nan-literal", Reason.NOT_JSON, _pose(pose=_at(x=float("nan")))),
    chunk_case("chunk-invalid-utf8-in-string", Reason.NOT_JSON,
               _chunk(robotId="ROBOT").replace(b"ROBOT", b"\x80\xff")),
    pose_case("pose-latin1-robot-id", Reason.NOT_JSON,
              _pose(robotId="ROBOT").replace(b"ROBOT", "r\u00e9".encode("latin-1"))),
    # missing_field
    chunk_case("chunk-no-row", Reason.MISSING_FIELD, _chunk(row=_DROP)),
    chunk_case("chunk-no-data", Reason.MISSING_FIELD, _chunk(pgmB64compressedData=_DROP)),
    pose_case("pose-no-pose", Reason.MISSING_FIELD, _pose(pose=_DROP)),
    pose_case("pose-no-orientation-w", Reason.MISSING_FIELD,
              _pose(pose={"position": {"x": 1, "y": 2}, "orientation": {"x": 0, "y": 0, "z": 0}})),
    # wrong_type
    chunk_case("chunk-row-as-string", Reason.WRONG_TYPE, _chunk(row="3")),
    chunk_case("chunk-row-as-float", Reason.WRONG_TYPE, _chunk(row=3.5)),
    chunk_case("chunk-json-array", Reason.WRONG_TYPE, b"[1, 2, 3]"),
    pose_case("pose-x-as-string", Reason.WRONG_TYPE, _pose(pose=_at(x="ten"))),
    pose_case("pose-timestamp-as-number", Reason.WRONG_TYPE, _pose(timestamp=1545348873)),
    # bad_robot_id
    chunk_case("chunk-empty-robot", Reason.BAD_ROBOT_ID, _chunk(robotId="")),
    chunk_case("chunk-robot-with-space", Reason.BAD_ROBOT_ID, _chunk(robotId="robot one")),
    chunk_case("chunk-robot-65-chars", Reason.BAD_ROBOT_ID, _chunk(robotId="r" * 65)),
    chunk_case("chunk-robot-trailing-newline", Reason.BAD_ROBOT_ID, _chunk(robotId="robot7\n")),
    pose_case("pose-robot-with-slash", Reason.BAD_ROBOT_ID, _pose(robotId="a/b"), "a/b"),
    # bad_base64
    chunk_case("chunk-listing14-literal-data", Reason.BAD_BASE64,
               _chunk(pgmB64compressedData="eNrt1rERwyAQRUG36HLcjlukABzIAbKPSAcDmt...")),
    chunk_case("chunk-base64-bad-padding", Reason.BAD_BASE64, _chunk(pgmB64compressedData="eNr")),
    # bad_zlib
    chunk_case("chunk-not-zlib", Reason.BAD_ZLIB,
               _chunk(pgmB64compressedData=base64.b64encode(b"P5 100 100 255").decode())),
    chunk_case("chunk-empty-data", Reason.BAD_ZLIB, _chunk(pgmB64compressedData="")),
    chunk_case("chunk-truncated-stream", Reason.BAD_ZLIB,
               _chunk(pgmB64compressedData=base64.b64encode(_full[: len(_full) // 2]).decode())),
    chunk_case("chunk-truncated-checksum", Reason.BAD_ZLIB,
               _chunk(pgmB64compressedData=base64.b64encode(_full[:-2]).decode())),
    chunk_case("chunk-bad-checksum", Reason.BAD_ZLIB,
               _chunk(pgmB64compressedData=base64.b64encode(_bad_check).decode())),
    # wrong_chunk_size
    chunk_case("chunk-too-small", Reason.WRONG_CHUNK_SIZE,
               _chunk(pgmB64compressedData=_b64z(bytes(99 * 100)))),
    chunk_case("chunk-too-big", Reason.WRONG_CHUNK_SIZE,
               _chunk(pgmB64compressedData=_b64z(bytes(100 * 101)))),
    chunk_case("chunk-size-of-other-meta", Reason.WRONG_CHUNK_SIZE, _chunk(),
               Limits().with_meta(MapMetaSet(width=500, height=500, chunk_width=50,
                                             chunk_height=50, chunk_rows=10, chunk_cols=10))),
    # out_of_map
    chunk_case("chunk-negative-row", Reason.OUT_OF_MAP, _chunk(row=-1)),
    chunk_case("chunk-negative-column", Reason.OUT_OF_MAP, _chunk(column=-1)),
    chunk_case("chunk-row-beyond-default-grid", Reason.OUT_OF_MAP, _chunk(row=1000)),
    chunk_case("chunk-row-beyond-meta", Reason.OUT_OF_MAP, _chunk(row=4, column=0),
               Limits().with_meta(META_4x5)),
    chunk_case("chunk-column-beyond-meta", Reason.OUT_OF_MAP, _chunk(row=0, column=5),
               Limits().with_meta(META_4x5)),
    # out_of_range
    pose_case("pose-x-beyond-1e6", Reason.OUT_OF_RANGE, _pose(pose=_at(x=1e7))),
    pose_case("pose-orientation-huge", Reason.OUT_OF_RANGE, _pose(pose=_at(q=(0, 0, 2e6, 1)))),
    pose_case("pose-battery-huge", Reason.OUT_OF_RANGE,
              _pose(status={"battery": {"battery_level": 1e9}})),
    pose_case("pose-path-point-huge", Reason.OUT_OF_RANGE,
              _pose(plannedPath=[{"x": 1, "y": 2}, {"x": -3e6, "y": 0}])),
    pose_case("pose-path-too-long", Reason.OUT_OF_RANGE,
              _pose(plannedPath=[{"x": 0.5, "y": 0.5}] * (MAX_PATH_POINTS + 1))),
    # bad_timestamp
    chunk_case("chunk-timestamp-words", Reason.BAD_TIMESTAMP, _chunk(timestamp="yesterday")),
    chunk_case("chunk-timestamp-month-13", Reason.BAD_TIMESTAMP,
               _chunk(timestamp="2026-13-01T00:00:00")),
    pose_case("pose-timestamp-empty", Reason.BAD_TIMESTAMP, _pose(timestamp="")),
    # timestamp_in_future
    chunk_case("chunk-1ms-beyond-skew", Reason.TIMESTAMP_IN_FUTURE, _chunk(timestamp=_ts(SKEW + 1))),
    pose_case("pose-one-hour-ahead", Reason.TIMESTAMP_IN_FUTURE, _pose(timestamp=_ts(3_600_000))),
    # timestamp_too_old
    chunk_case("chunk-listing14-2018-timestamp", Reason.TIMESTAMP_TOO_OLD,
               _chunk(timestamp="2018-12-20T23:34:33")),
    pose_case("pose-1ms-beyond-retention", Reason.TIMESTAMP_TOO_OLD,
              _pose(timestamp=_ts(-RETENTION - 1))),
    # robot_id_mismatch
    pose_case("pose-topic-names-other-robot", Reason.ROBOT_ID_MISMATCH, _pose(), "other"),
    pose_case("pose-topic-with-extra-level", Reason.ROBOT_ID_MISMATCH, _pose(), "blabla/x"),
    # oversized
    chunk_case("chunk-oversized", Reason.OVERSIZED,
               _chunk(robotId="r", pgmB64compressedData="A" * (256 * 1024))),
    pose_case("pose-oversized-garbage-checked-first", Reason.OVERSIZED, b"\xff" * 2048,
              limits=Limits(max_message_bytes=1024)),
    # a 2 KB message nested ~1,000 levels deep (msgspec raises RecursionError)
    pose_case("pose-nested-1000-deep", Reason.TOO_DEEP, b'{"x":' + b"[" * 1000 + b"]" * 1000 + b"}"),
    chunk_case("chunk-nested-5000-deep", Reason.TOO_DEEP, b'{"x":' + b"[" * 5000 + b"]" * 5000 + b"}"),
]


@pytest.mark.parametrize("case", BAD_CASES, ids=[c.id for c in BAD_CASES])
def test_bad_message_is_rejected_with_its_reason(case: Bad) -> None:
    """Each concrete bad message is rejected (never raises) with the expected reason code."""
    result = case.decode()
    assert isinstance(result, Rejection), f"accepted: {result}"
    assert result.reason is case.reason, result.detail
    assert result.detail


def test_every_reason_code_has_a_bad_message() -> None:
    """Every Reason of the 2019 codec has a case above; the router's and the gateway's
    (unknown_topic, internal_error, record_too_large, too_many_new_robots) and the VDA 5050
    ingest's (vda_*) and the command answers' are tested in tests/ingest (test_ingestor.py,
    test_vda5050.py, test_command_responses.py)."""
    covered = {c.reason for c in BAD_CASES}
    elsewhere = {Reason.UNKNOWN_TOPIC, Reason.INTERNAL_ERROR, Reason.RECORD_TOO_LARGE,
                 Reason.TOO_MANY_NEW_ROBOTS, Reason.VDA_SCHEMA, Reason.VDA_UNSUPPORTED_VERSION,
                 Reason.VDA_NO_POSITION, Reason.BAD_COMMAND_RESPONSE, Reason.UNKNOWN_COMMAND,
                 Reason.NOT_ITS_COMMAND}
    assert covered == set(Reason) - elsewhere


def test_zlib_bomb_is_bounded_to_one_chunk() -> None:
    """A 50 MB zlib bomb is rejected as wrong_chunk_size without inflating it all."""
    bomb = zlib.compress(bytes(50_000_000), 9)
    data = _chunk(pgmB64compressedData=base64.b64encode(bomb).decode())
    assert len(data) < Limits().max_message_bytes
    tracemalloc.start()
    try:
        result = decode_chunk_create(data, NOW, Limits())
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert isinstance(result, Rejection) and result.reason is Reason.WRONG_CHUNK_SIZE
    assert "more than 10000" in result.detail
    assert peak < 5_000_000, f"decoding allocated {peak} bytes"


def test_huge_json_number_is_rejected() -> None:
    """1e400 (infinity once parsed) never reaches a PoseReported."""
    data = _pose(pose=_at(y=123456.5)).replace(b"123456.5", b"1e400")
    assert b"1e400" in data
    result = decode_coordinates("blabla", data, NOW, Limits())
    assert isinstance(result, Rejection)
    assert result.reason in (Reason.WRONG_TYPE, Reason.OUT_OF_RANGE, Reason.NOT_JSON)


def test_out_of_range_detail_names_the_limit() -> None:
    """An out-of-range pose says which bound it broke."""
    result = decode_coordinates("blabla", _pose(pose=_at(x=-2e6)), NOW, Limits())
    assert isinstance(result, Rejection) and "1e+06" in result.detail


# --- boundaries that must still be accepted -------------------------------------------


@pytest.mark.parametrize("offset", [SKEW, SKEW - 1, 0, -RETENTION, -RETENTION + 1],
                         ids=["at-skew", "inside-skew", "now", "at-retention", "inside-retention"])
def test_timestamp_within_skew_and_retention_is_accepted(offset: int) -> None:
    """Timestamps up to the future skew and back to the retention edge are accepted as sent."""
    result = decode_chunk_create(_chunk(timestamp=_ts(offset)), NOW, Limits())
    assert isinstance(result, Envelope), result
    assert result.event_time_ms == NOW + offset


def test_chunk_inside_meta_grid_is_accepted() -> None:
    """The last row and column of a 4 x 5 grid are inside the map."""
    result = decode_chunk_create(_chunk(row=3, column=4), NOW, Limits().with_meta(META_4x5))
    assert isinstance(result, Envelope)
    assert (result.payload.row, result.payload.column) == (3, 4)


def test_chunk_size_follows_meta() -> None:
    """With a 50 x 50 meta a 50 x 50 chunk is accepted and carries the meta's size."""
    limits = Limits().with_meta(MapMetaSet(width=100, height=100, chunk_width=50, chunk_height=50,
                                           chunk_rows=2, chunk_cols=2))
    result = decode_chunk_create(_chunk(row=1, column=1, pgmB64compressedData=_b64z(bytes(2500))),
                                 NOW, limits)
    assert isinstance(result, Envelope)
    assert (result.payload.width, result.payload.height) == (50, 50)


def test_path_of_max_points_is_accepted() -> None:
    """A plannedPath of exactly MAX_PATH_POINTS points is accepted."""
    path = [{"x": i / 10, "y": -i / 10} for i in range(MAX_PATH_POINTS)]
    result = decode_coordinates("blabla", _pose(plannedPath=path), NOW, Limits())
    assert isinstance(result, Envelope)
    assert len(result.payload.path) == MAX_PATH_POINTS
    assert result.payload.path[7] == (0.7, -0.7)


def test_robot_id_of_64_allowed_characters_is_accepted() -> None:
    """All characters of the robot id alphabet, up to 64 of them, are accepted."""
    robot = "Az09_.:@-" + "x" * 55
    result = decode_chunk_create(_chunk(robotId=robot), NOW, Limits())
    assert isinstance(result, Envelope) and result.robot_id == robot


# --- valid 2019 messages ----------------------------------------------------------------


def test_listing14_message_decodes(wire) -> None:
    """Listing 14 with real pixels and a current timestamp becomes a ChunkUpdated."""
    data = wire.chunk()
    result = decode_chunk_create(data, NOW + 123, Limits())
    assert isinstance(result, Envelope), result
    p = result.payload
    assert isinstance(p, ChunkUpdated)
    assert result.type == "chunk.updated" and result.version == 1
    assert result.robot_id == "lkjlkj"
    assert (result.event_time_ms, result.receive_time_ms) == (NOW, NOW + 123)
    assert (p.row, p.column, p.width, p.height) == (3, 2, 100, 100)
    sent = base64.b64decode(msgspec.json.decode(data)["pgmB64compressedData"])
    assert p.data == sent  # kept exactly as the robot sent it
    assert p.content_hash == content_hash(bytes([205]) * 10_000)
    assert len(p.content_hash) == 16
    assert result.event_id == event_id_for("lkjlkj", NOW, p)


def test_listing16_message_decodes(wire) -> None:
    """Listing 16 (integers, string flags) becomes a PoseReported with floats and flags as sent."""
    result = decode_coordinates("blabla", wire.pose(), NOW, Limits())
    assert isinstance(result, Envelope), result
    p = result.payload
    assert isinstance(p, PoseReported)
    assert result.type == "pose.reported" and result.robot_id == "blabla"
    assert result.event_time_ms == NOW
    assert p.position == (10.0, 20.0, 0.0)
    assert all(isinstance(v, float) for v in p.position + p.orientation)
    assert p.orientation == (0.0, 0.0, 0.0, 1.0)
    assert p.battery_level == 3.0
    assert p.charging == "sdf" and p.loaded == "dfs"
    assert p.path is None


def test_pose_with_boolean_flags_and_path_decodes() -> None:
    """Boolean charging/loaded stay booleans, z defaults to 0 and the path becomes pairs."""
    data = encode_coordinates("r2", _ts(), 1.5, -2.25, (0, 0, 0.7071, 0.7071), 55.5,
                              charging=True, loaded=False, path=[(1, 2), (3.5, 4)])
    doc = msgspec.json.decode(data)
    del doc["pose"]["position"]["z"]
    result = decode_coordinates("r2", msgspec.json.encode(doc), NOW, Limits())
    assert isinstance(result, Envelope), result
    p = result.payload
    assert p.position == (1.5, -2.25, 0.0)
    assert p.charging is True and p.loaded is False
    assert p.battery_level == 55.5
    assert p.path == ((1.0, 2.0), (3.5, 4.0))


def test_pose_without_status_decodes() -> None:
    """status is optional: battery and flags are then None."""
    result = decode_coordinates("blabla", _pose(status=_DROP), NOW, Limits())
    assert isinstance(result, Envelope)
    assert (result.payload.battery_level, result.payload.charging, result.payload.loaded) == (
        None, None, None)


def test_encode_chunk_create_round_trips() -> None:
    """What encode_chunk_create writes, decode_chunk_create accepts with the same pixels."""
    pixels = bytes(i % 251 for i in range(10_000))
    result = decode_chunk_create(encode_chunk_create(7, 9, pixels, _ts(-1000), "rx"), NOW, Limits())
    assert isinstance(result, Envelope)
    assert zlib.decompress(result.payload.data) == pixels
    assert (result.payload.row, result.payload.column, result.event_time_ms) == (7, 9, NOW - 1000)


@pytest.mark.parametrize("text,expected", [
    ("2026-11-21T10:00:00", NOW),
    ("2026-11-21T10:00:00Z", NOW),
    ("2026-11-21T10:00:00+00:00", NOW),
    ("2026-11-21T11:30:00+01:30", NOW),
    ("2026-11-21T10:00:00.250", NOW + 250),
])
def test_timestamp_without_zone_is_utc(text: str, expected: int) -> None:
    """A timestamp without a zone means UTC; explicit offsets are honoured."""
    assert parse_timestamp(text) == expected


def test_pose_timestamp_without_zone_is_utc() -> None:
    """A zoneless message timestamp is stored as the same instant as its UTC spelling."""
    plain = decode_coordinates("blabla", _pose(timestamp="2026-11-21T09:59:00"), NOW, Limits())
    zoned = decode_coordinates("blabla", _pose(timestamp="2026-11-21T10:59:00+01:00"), NOW,
                               Limits())
    assert plain.event_time_ms == zoned.event_time_ms == NOW - 60_000


@pytest.mark.parametrize("ms,text", [(NOW, "2026-11-21T10:00:00"),
                                     (NOW + 5, "2026-11-21T10:00:00.005")])
def test_format_timestamp_is_2019_style(ms: int, text: str) -> None:
    """format_timestamp writes the 2019 style (no zone, milliseconds only when needed)."""
    assert format_timestamp(ms) == text
    assert parse_timestamp(text) == ms


@settings(max_examples=200, deadline=None, database=None)
@given(ms=st.lists(st.integers(-10**12, 4 * 10**12) | st.integers(0, 10**6).map(lambda s: s * 1000)))
def test_format_timestamps_equals_format_timestamp(ms: list[int]) -> None:
    """format_timestamps (vectorised, for whole maps) writes exactly what format_timestamp does."""
    assert format_timestamps(ms) == [format_timestamp(m) for m in ms]


# --- nothing raises, whatever arrives -----------------------------------------------------

SMALL = Limits(chunk_width=4, chunk_height=4, chunk_rows=8, chunk_cols=8,
               max_message_bytes=64 * 1024)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=16,
)
json_objects = st.dictionaries(st.text(max_size=12), json_values, max_size=6)
robot_ids = st.from_regex(r"[A-Za-z0-9_.:@-]{1,8}", fullmatch=True) | st.text(max_size=10)
offsets = st.datetimes().map(lambda d: d.isoformat())
zones = st.timedeltas(min_value=-timedelta(hours=23, minutes=59),
                      max_value=timedelta(hours=23, minutes=59)).map(timezone)
timestamps = (
    st.integers(-10 * DAY, 10 * DAY).map(_ts)
    | st.datetimes().map(lambda d: d.isoformat())
    | st.datetimes(timezones=zones).map(lambda d: d.isoformat())
    | st.text(max_size=30)
)
pixel_data = (
    st.binary(min_size=0, max_size=40).map(_b64z)
    | st.binary(max_size=40).map(lambda b: base64.b64encode(b).decode())
    | st.binary(min_size=16, max_size=16).map(lambda b: _b64z(b))
    | st.text(max_size=30)
)
any_value = json_values
chunk_like = st.fixed_dictionaries({}, optional={
    "pgmB64compressedData": pixel_data | any_value,
    "row": st.integers(-3, 10) | any_value,
    "column": st.integers(-3, 10) | any_value,
    "timestamp": timestamps | any_value,
    "robotId": robot_ids | any_value,
})
numbers = st.floats() | st.integers(-10**7, 10**7)
vec = st.fixed_dictionaries({"x": numbers, "y": numbers}, optional={"z": numbers})
quat = st.fixed_dictionaries({"x": numbers, "y": numbers, "z": numbers, "w": numbers})
pose_like = st.fixed_dictionaries({}, optional={
    "robotId": robot_ids | any_value,
    "timestamp": timestamps | any_value,
    "pose": st.fixed_dictionaries({"position": vec, "orientation": quat}) | any_value,
    "status": st.fixed_dictionaries({}, optional={
        "battery": st.fixed_dictionaries({}, optional={
            "battery_level": numbers | st.none(), "charging": any_value}),
        "loaded": any_value}) | any_value,
    "plannedPath": st.lists(st.fixed_dictionaries({"x": numbers, "y": numbers}), max_size=5)
    | any_value,
})

PROPERTY = settings(max_examples=200, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


def _as_json(obj) -> bytes:
    return json.dumps(obj).encode()  # allow_nan: NaN/Infinity literals are not JSON


def _check_chunk(result, limits: Limits) -> None:
    assert isinstance(result, (Envelope, Rejection)), result
    if isinstance(result, Rejection):
        assert isinstance(result.reason, Reason) and result.reason is not Reason.UNKNOWN_TOPIC
        return
    p = result.payload
    assert 0 <= p.row < limits.chunk_rows and 0 <= p.column < limits.chunk_cols
    pixels = zlib.decompress(p.data)
    assert len(pixels) == limits.chunk_width * limits.chunk_height
    assert p.content_hash == content_hash(pixels)
    assert NOW - limits.retention_ms <= result.event_time_ms <= NOW + limits.max_future_skew_ms


def _check_pose(result, topic_robot: str) -> None:
    assert isinstance(result, (Envelope, Rejection)), result
    if isinstance(result, Rejection):
        assert isinstance(result.reason, Reason) and result.reason is not Reason.UNKNOWN_TOPIC
        return
    assert result.robot_id == topic_robot
    p = result.payload
    values = [*p.position, *p.orientation, *(c for pt in p.path or () for c in pt)]
    if p.battery_level is not None:
        values.append(p.battery_level)
    assert all(math.isfinite(v) and abs(v) < 1e6 for v in values)


@PROPERTY
@given(data=st.binary(max_size=300))
def test_decoders_never_raise_on_arbitrary_bytes(data: bytes) -> None:
    """Arbitrary bytes give an Envelope or a Rejection from both decoders, never an exception."""
    _check_chunk(decode_chunk_create(data, NOW, SMALL), SMALL)
    _check_pose(decode_coordinates("r1", data, NOW, SMALL), "r1")


@PROPERTY
@given(obj=json_objects | json_values)
def test_decoders_never_raise_on_arbitrary_json(obj) -> None:
    """Arbitrary JSON documents give an Envelope or a Rejection, never an exception."""
    data = _as_json(obj)
    _check_chunk(decode_chunk_create(data, NOW, SMALL), SMALL)
    _check_pose(decode_coordinates("r1", data, NOW, SMALL), "r1")


@PROPERTY
@given(doc=chunk_like | pose_like, junk=st.binary(min_size=1, max_size=12), where=st.integers(0))
def test_decoders_never_raise_on_bytes_spliced_into_json(doc: dict, junk: bytes,
                                                        where: int) -> None:
    """Arbitrary bytes (invalid UTF-8 included) inside a JSON string never make a decoder raise."""
    data = _as_json({**doc, "robotId": "MARKER"})
    data = data.replace(b"MARKER", junk, 1)
    data = data[: where % (len(data) + 1)] + junk + data[where % (len(data) + 1):] \
        if where % 3 == 0 else data
    _check_chunk(decode_chunk_create(data, NOW, SMALL), SMALL)
    _check_pose(decode_coordinates("r1", data, NOW, SMALL), "r1")


@PROPERTY
@given(doc=chunk_like, limits=st.sampled_from([SMALL, Limits()]))
def test_chunk_decoder_never_raises_on_near_valid_messages(doc: dict, limits: Limits) -> None:
    """Near-valid chunk messages decode or reject; accepted ones respect grid, size and time."""
    _check_chunk(decode_chunk_create(_as_json(doc), NOW, limits), limits)


@PROPERTY
@given(doc=pose_like, same_robot=st.booleans())
def test_pose_decoder_never_raises_on_near_valid_messages(doc: dict, same_robot: bool) -> None:
    """Near-valid pose messages decode or reject; accepted ones are finite, bounded, same robot."""
    robot = doc.get("robotId") if same_robot and isinstance(doc.get("robotId"), str) else "r1"
    _check_pose(decode_coordinates(robot, _as_json(doc), NOW, SMALL), robot)


@pytest.mark.parametrize("field,value", [
    ("charging", "x" * 120_000), ("loaded", "y" * 65), ("timestamp", "2" * 65), ("robotId", "r" * 300)])
def test_long_free_text_fields_are_refused_while_decoding(wire, field, value) -> None:
    """charging/loaded over 64 characters, timestamps over 64 and robot ids over 256: wrong_type,
    and the reason does not echo the long value."""
    from mapservice.core.wire2019 import Limits, Reason, decode_coordinates

    doc = wire.pose_doc()
    if field == "charging":
        doc["status"]["battery"]["charging"] = value
    elif field == "loaded":
        doc["status"]["loaded"] = value
    else:
        doc[field] = value
    got = decode_coordinates(doc["robotId"], json.dumps(doc).encode(), wire.now_ms, Limits())
    assert got.reason == Reason.WRONG_TYPE, got
    assert len(got.detail) < 300


def test_format_timestamp_per_minute_cache_equals_datetime_everywhere() -> None:
    """The cached-prefix formatter gives datetime's text for whole seconds, milliseconds,
    minute edges, before 1970 and far ahead, and for a float."""
    import random

    from mapservice.core.wire2019 import _format_timestamp_datetime, format_timestamp

    rng = random.Random(16)
    samples = [0, -1, 59_999, 60_000, 1_763_911_229_435, 1_763_911_229_000, -62_135_596_800_000,
               253_402_300_799_000] + [rng.randrange(-10**12, 4 * 10**12) for _ in range(5000)]
    for ms in samples:
        assert format_timestamp(ms) == _format_timestamp_datetime(ms), ms
    assert format_timestamp(1_763_911_229_435.0) == "2025-11-23T15:20:29.435"
