"""The 2019 wire contract (appendix A, listings 14 and 16): every rejection, one bad
message per reason code."""

from __future__ import annotations

import base64
import tracemalloc
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import pytest

from mapservice.core.events import Envelope, MapMetaSet
from mapservice.core.wire2019 import (
    MAX_PATH_POINTS,
    Limits,
    Reason,
    Rejection,
    decode_chunk_create,
    decode_coordinates,
)
from tests.mapservice.core.wire2019_messages import (
    DROP,
    NOW,
    RETENTION,
    SKEW,
    META_4x5,
    at_pose,
    b64z,
    chunk_json,
    pose_json,
    stamp,
)

# --- one concrete bad message per reason code -----------------------------------------


@dataclass(frozen=True)
class Bad:
    id: str
    reason: Reason
    decode: Callable[[], Envelope | Rejection]


def chunk_case(id_: str, reason: Reason, data: bytes, limits: Limits = Limits()) -> Bad:
    return Bad(id_, reason, lambda: decode_chunk_create(data, NOW, limits))


def pose_case(
    id_: str, reason: Reason, data: bytes, topic_robot: str = "blabla", limits: Limits = Limits()
) -> Bad:
    return Bad(id_, reason, lambda: decode_coordinates(topic_robot, data, NOW, limits))


_pixels = bytes(range(256)) * 39 + bytes(16)  # exactly 10_000 bytes
_full = zlib.compress(_pixels)
_bad_check = _full[:-1] + bytes([_full[-1] ^ 0xFF])

BAD_CASES = [
    # not_json
    chunk_case("chunk-not-json", Reason.NOT_JSON, b'{"row": 3,'),
    chunk_case("chunk-empty-body", Reason.NOT_JSON, b""),
    pose_case("pose-binary-garbage", Reason.NOT_JSON, b"\xff\xfe\x00garbage"),
    pose_case("pose-nan-literal", Reason.NOT_JSON, pose_json(pose=at_pose(x=float("nan")))),
    chunk_case(
        "chunk-invalid-utf8-in-string",
        Reason.NOT_JSON,
        chunk_json(robotId="ROBOT").replace(b"ROBOT", b"\x80\xff"),
    ),
    pose_case(
        "pose-latin1-robot-id",
        Reason.NOT_JSON,
        pose_json(robotId="ROBOT").replace(b"ROBOT", "r\u00e9".encode("latin-1")),
    ),
    # missing_field
    chunk_case("chunk-no-row", Reason.MISSING_FIELD, chunk_json(row=DROP)),
    chunk_case("chunk-no-data", Reason.MISSING_FIELD, chunk_json(pgmB64compressedData=DROP)),
    pose_case("pose-no-pose", Reason.MISSING_FIELD, pose_json(pose=DROP)),
    pose_case(
        "pose-no-orientation-w",
        Reason.MISSING_FIELD,
        pose_json(pose={"position": {"x": 1, "y": 2}, "orientation": {"x": 0, "y": 0, "z": 0}}),
    ),
    # wrong_type
    chunk_case("chunk-row-as-string", Reason.WRONG_TYPE, chunk_json(row="3")),
    chunk_case("chunk-row-as-float", Reason.WRONG_TYPE, chunk_json(row=3.5)),
    chunk_case("chunk-json-array", Reason.WRONG_TYPE, b"[1, 2, 3]"),
    pose_case("pose-x-as-string", Reason.WRONG_TYPE, pose_json(pose=at_pose(x="ten"))),
    pose_case("pose-timestamp-as-number", Reason.WRONG_TYPE, pose_json(timestamp=1545348873)),
    # bad_robot_id
    chunk_case("chunk-empty-robot", Reason.BAD_ROBOT_ID, chunk_json(robotId="")),
    chunk_case("chunk-robot-with-space", Reason.BAD_ROBOT_ID, chunk_json(robotId="robot one")),
    chunk_case("chunk-robot-65-chars", Reason.BAD_ROBOT_ID, chunk_json(robotId="r" * 65)),
    chunk_case("chunk-robot-trailing-newline", Reason.BAD_ROBOT_ID, chunk_json(robotId="robot7\n")),
    pose_case("pose-robot-with-slash", Reason.BAD_ROBOT_ID, pose_json(robotId="a/b"), "a/b"),
    # bad_base64
    chunk_case(
        "chunk-listing14-literal-data",
        Reason.BAD_BASE64,
        chunk_json(pgmB64compressedData="eNrt1rERwyAQRUG36HLcjlukABzIAbKPSAcDmt..."),
    ),
    chunk_case(
        "chunk-base64-bad-padding", Reason.BAD_BASE64, chunk_json(pgmB64compressedData="eNr")
    ),
    # bad_zlib
    chunk_case(
        "chunk-not-zlib",
        Reason.BAD_ZLIB,
        chunk_json(pgmB64compressedData=base64.b64encode(b"P5 100 100 255").decode()),
    ),
    chunk_case("chunk-empty-data", Reason.BAD_ZLIB, chunk_json(pgmB64compressedData="")),
    chunk_case(
        "chunk-truncated-stream",
        Reason.BAD_ZLIB,
        chunk_json(pgmB64compressedData=base64.b64encode(_full[: len(_full) // 2]).decode()),
    ),
    chunk_case(
        "chunk-truncated-checksum",
        Reason.BAD_ZLIB,
        chunk_json(pgmB64compressedData=base64.b64encode(_full[:-2]).decode()),
    ),
    chunk_case(
        "chunk-bad-checksum",
        Reason.BAD_ZLIB,
        chunk_json(pgmB64compressedData=base64.b64encode(_bad_check).decode()),
    ),
    # wrong_chunk_size
    chunk_case(
        "chunk-too-small",
        Reason.WRONG_CHUNK_SIZE,
        chunk_json(pgmB64compressedData=b64z(bytes(99 * 100))),
    ),
    chunk_case(
        "chunk-too-big",
        Reason.WRONG_CHUNK_SIZE,
        chunk_json(pgmB64compressedData=b64z(bytes(100 * 101))),
    ),
    chunk_case(
        "chunk-size-of-other-meta",
        Reason.WRONG_CHUNK_SIZE,
        chunk_json(),
        Limits().with_meta(
            MapMetaSet(
                width=500, height=500, chunk_width=50, chunk_height=50, chunk_rows=10, chunk_cols=10
            )
        ),
    ),
    # out_of_map
    chunk_case("chunk-negative-row", Reason.OUT_OF_MAP, chunk_json(row=-1)),
    chunk_case("chunk-negative-column", Reason.OUT_OF_MAP, chunk_json(column=-1)),
    chunk_case("chunk-row-beyond-default-grid", Reason.OUT_OF_MAP, chunk_json(row=1000)),
    chunk_case(
        "chunk-row-beyond-meta",
        Reason.OUT_OF_MAP,
        chunk_json(row=4, column=0),
        Limits().with_meta(META_4x5),
    ),
    chunk_case(
        "chunk-column-beyond-meta",
        Reason.OUT_OF_MAP,
        chunk_json(row=0, column=5),
        Limits().with_meta(META_4x5),
    ),
    # out_of_range
    pose_case("pose-x-beyond-1e6", Reason.OUT_OF_RANGE, pose_json(pose=at_pose(x=1e7))),
    pose_case(
        "pose-orientation-huge", Reason.OUT_OF_RANGE, pose_json(pose=at_pose(q=(0, 0, 2e6, 1)))
    ),
    pose_case(
        "pose-battery-huge",
        Reason.OUT_OF_RANGE,
        pose_json(status={"battery": {"battery_level": 1e9}}),
    ),
    pose_case(
        "pose-path-point-huge",
        Reason.OUT_OF_RANGE,
        pose_json(plannedPath=[{"x": 1, "y": 2}, {"x": -3e6, "y": 0}]),
    ),
    pose_case(
        "pose-path-too-long",
        Reason.OUT_OF_RANGE,
        pose_json(plannedPath=[{"x": 0.5, "y": 0.5}] * (MAX_PATH_POINTS + 1)),
    ),
    # bad_timestamp
    chunk_case("chunk-timestamp-words", Reason.BAD_TIMESTAMP, chunk_json(timestamp="yesterday")),
    chunk_case(
        "chunk-timestamp-month-13",
        Reason.BAD_TIMESTAMP,
        chunk_json(timestamp="2026-13-01T00:00:00"),
    ),
    pose_case("pose-timestamp-empty", Reason.BAD_TIMESTAMP, pose_json(timestamp="")),
    # timestamp_in_future
    chunk_case(
        "chunk-1ms-beyond-skew", Reason.TIMESTAMP_IN_FUTURE, chunk_json(timestamp=stamp(SKEW + 1))
    ),
    pose_case(
        "pose-one-hour-ahead", Reason.TIMESTAMP_IN_FUTURE, pose_json(timestamp=stamp(3_600_000))
    ),
    # timestamp_too_old
    chunk_case(
        "chunk-listing14-2018-timestamp",
        Reason.TIMESTAMP_TOO_OLD,
        chunk_json(timestamp="2018-12-20T23:34:33"),
    ),
    pose_case(
        "pose-1ms-beyond-retention",
        Reason.TIMESTAMP_TOO_OLD,
        pose_json(timestamp=stamp(-RETENTION - 1)),
    ),
    # robot_id_mismatch
    pose_case("pose-topic-names-other-robot", Reason.ROBOT_ID_MISMATCH, pose_json(), "other"),
    pose_case("pose-topic-with-extra-level", Reason.ROBOT_ID_MISMATCH, pose_json(), "blabla/x"),
    # oversized
    chunk_case(
        "chunk-oversized",
        Reason.OVERSIZED,
        chunk_json(robotId="r", pgmB64compressedData="A" * (256 * 1024)),
    ),
    pose_case(
        "pose-oversized-garbage-checked-first",
        Reason.OVERSIZED,
        b"\xff" * 2048,
        limits=Limits(max_message_bytes=1024),
    ),
    # a 2 KB message nested ~1,000 levels deep (msgspec raises RecursionError)
    pose_case(
        "pose-nested-1000-deep", Reason.TOO_DEEP, b'{"x":' + b"[" * 1000 + b"]" * 1000 + b"}"
    ),
    chunk_case(
        "chunk-nested-5000-deep", Reason.TOO_DEEP, b'{"x":' + b"[" * 5000 + b"]" * 5000 + b"}"
    ),
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
    test_ingestor_poison.py, test_mqtt_gateway.py, test_vda5050.py,
    test_command_responses.py); the map meta's (grid_short_of_map) in
    tests/ingest/test_intake_channels.py."""
    covered = {c.reason for c in BAD_CASES}
    elsewhere = {
        Reason.UNKNOWN_TOPIC,
        Reason.INTERNAL_ERROR,
        Reason.RECORD_TOO_LARGE,
        Reason.TOO_MANY_NEW_ROBOTS,
        Reason.VDA_SCHEMA,
        Reason.VDA_UNSUPPORTED_VERSION,
        Reason.VDA_NO_POSITION,
        Reason.BAD_COMMAND_RESPONSE,
        Reason.UNKNOWN_COMMAND,
        Reason.NOT_ITS_COMMAND,
        Reason.GRID_SHORT_OF_MAP,
    }
    assert covered == set(Reason) - elsewhere


def test_zlib_bomb_is_bounded_to_one_chunk() -> None:
    """A 50 MB zlib bomb is rejected as wrong_chunk_size without inflating it all."""
    bomb = zlib.compress(bytes(50_000_000), 9)
    data = chunk_json(pgmB64compressedData=base64.b64encode(bomb).decode())
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
    data = pose_json(pose=at_pose(y=123456.5)).replace(b"123456.5", b"1e400")
    assert b"1e400" in data
    result = decode_coordinates("blabla", data, NOW, Limits())
    assert isinstance(result, Rejection)
    assert result.reason in (Reason.WRONG_TYPE, Reason.OUT_OF_RANGE, Reason.NOT_JSON)


def test_out_of_range_detail_names_the_limit() -> None:
    """An out-of-range pose says which bound it broke."""
    result = decode_coordinates("blabla", pose_json(pose=at_pose(x=-2e6)), NOW, Limits())
    assert isinstance(result, Rejection) and "1e+06" in result.detail
