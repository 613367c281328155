"""The 2019 wire decoders never raise, whatever arrives: arbitrary bytes and JSON, bytes
spliced into JSON, near-valid messages; accepted ones respect the limits."""

from __future__ import annotations

import base64
import json
import math
import zlib
from datetime import timedelta, timezone

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.events import Envelope
from mapservice.core.wire2019 import (
    Limits,
    Reason,
    Rejection,
    content_hash,
    decode_chunk_create,
    decode_coordinates,
)
from tests.mapservice.core.wire2019_messages import DAY, NOW, b64z, stamp

# --- nothing raises, whatever arrives -----------------------------------------------------

SMALL = Limits(
    chunk_width=4, chunk_height=4, chunk_rows=8, chunk_cols=8, max_message_bytes=64 * 1024
)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=16,
)
json_objects = st.dictionaries(st.text(max_size=12), json_values, max_size=6)
robot_ids = st.from_regex(r"[A-Za-z0-9_.:@-]{1,8}", fullmatch=True) | st.text(max_size=10)
offsets = st.datetimes().map(lambda d: d.isoformat())
zones = st.timedeltas(
    min_value=-timedelta(hours=23, minutes=59), max_value=timedelta(hours=23, minutes=59)
).map(timezone)
timestamps = (
    st.integers(-10 * DAY, 10 * DAY).map(stamp)
    | st.datetimes().map(lambda d: d.isoformat())
    | st.datetimes(timezones=zones).map(lambda d: d.isoformat())
    | st.text(max_size=30)
)
pixel_data = (
    st.binary(min_size=0, max_size=40).map(b64z)
    | st.binary(max_size=40).map(lambda b: base64.b64encode(b).decode())
    | st.binary(min_size=16, max_size=16).map(lambda b: b64z(b))
    | st.text(max_size=30)
)
any_value = json_values
chunk_like = st.fixed_dictionaries(
    {},
    optional={
        "pgmB64compressedData": pixel_data | any_value,
        "row": st.integers(-3, 10) | any_value,
        "column": st.integers(-3, 10) | any_value,
        "timestamp": timestamps | any_value,
        "robotId": robot_ids | any_value,
    },
)
numbers = st.floats() | st.integers(-(10**7), 10**7)
vec = st.fixed_dictionaries({"x": numbers, "y": numbers}, optional={"z": numbers})
quat = st.fixed_dictionaries({"x": numbers, "y": numbers, "z": numbers, "w": numbers})
pose_like = st.fixed_dictionaries(
    {},
    optional={
        "robotId": robot_ids | any_value,
        "timestamp": timestamps | any_value,
        "pose": st.fixed_dictionaries({"position": vec, "orientation": quat}) | any_value,
        "status": st.fixed_dictionaries(
            {},
            optional={
                "battery": st.fixed_dictionaries(
                    {}, optional={"battery_level": numbers | st.none(), "charging": any_value}
                ),
                "loaded": any_value,
            },
        )
        | any_value,
        "plannedPath": st.lists(st.fixed_dictionaries({"x": numbers, "y": numbers}), max_size=5)
        | any_value,
    },
)

PROPERTY = settings(
    max_examples=200, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)


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
def test_decoders_never_raise_on_bytes_spliced_into_json(
    doc: dict, junk: bytes, where: int
) -> None:
    """Arbitrary bytes (invalid UTF-8 included) inside a JSON string never make a decoder raise."""
    data = _as_json({**doc, "robotId": "MARKER"})
    data = data.replace(b"MARKER", junk, 1)
    data = (
        data[: where % (len(data) + 1)] + junk + data[where % (len(data) + 1) :]
        if where % 3 == 0
        else data
    )
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
