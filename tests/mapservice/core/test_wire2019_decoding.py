"""The 2019 wire contract (appendix A, listings 14 and 16): what is accepted and how it
decodes, boundaries included, and the 2019 timestamp format."""

from __future__ import annotations

import base64
import json
import zlib

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core.events import ChunkUpdated, Envelope, MapMetaSet, PoseReported, event_id_for
from mapservice.core.wire2019 import (
    MAX_PATH_POINTS,
    Limits,
    content_hash,
    decode_chunk_create,
    decode_coordinates,
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
    format_timestamps,
    parse_timestamp,
)
from tests.mapservice.core.wire2019_messages import (
    DROP,
    NOW,
    RETENTION,
    SKEW,
    META_4x5,
    b64z,
    chunk_json,
    pose_json,
    stamp,
)

# --- boundaries that must still be accepted -------------------------------------------


@pytest.mark.parametrize(
    "offset",
    [SKEW, SKEW - 1, 0, -RETENTION, -RETENTION + 1],
    ids=["at-skew", "inside-skew", "now", "at-retention", "inside-retention"],
)
def test_timestamp_within_skew_and_retention_is_accepted(offset: int) -> None:
    """Timestamps up to the future skew and back to the retention edge are accepted as sent."""
    result = decode_chunk_create(chunk_json(timestamp=stamp(offset)), NOW, Limits())
    assert isinstance(result, Envelope), result
    assert result.event_time_ms == NOW + offset


def test_chunk_inside_meta_grid_is_accepted() -> None:
    """The last row and column of a 4 x 5 grid are inside the map."""
    result = decode_chunk_create(chunk_json(row=3, column=4), NOW, Limits().with_meta(META_4x5))
    assert isinstance(result, Envelope)
    assert (result.payload.row, result.payload.column) == (3, 4)


def test_chunk_size_follows_meta() -> None:
    """With a 50 x 50 meta a 50 x 50 chunk is accepted and carries the meta's size."""
    limits = Limits().with_meta(
        MapMetaSet(
            width=100, height=100, chunk_width=50, chunk_height=50, chunk_rows=2, chunk_cols=2
        )
    )
    result = decode_chunk_create(
        chunk_json(row=1, column=1, pgmB64compressedData=b64z(bytes(2500))), NOW, limits
    )
    assert isinstance(result, Envelope)
    assert (result.payload.width, result.payload.height) == (50, 50)


def test_path_of_max_points_is_accepted() -> None:
    """A plannedPath of exactly MAX_PATH_POINTS points is accepted."""
    path = [{"x": i / 10, "y": -i / 10} for i in range(MAX_PATH_POINTS)]
    result = decode_coordinates("blabla", pose_json(plannedPath=path), NOW, Limits())
    assert isinstance(result, Envelope)
    assert len(result.payload.path) == MAX_PATH_POINTS
    assert result.payload.path[7] == (0.7, -0.7)


def test_robot_id_of_64_allowed_characters_is_accepted() -> None:
    """All characters of the robot id alphabet, up to 64 of them, are accepted."""
    robot = "Az09_.:@-" + "x" * 55
    result = decode_chunk_create(chunk_json(robotId=robot), NOW, Limits())
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
    data = encode_coordinates(
        "r2",
        stamp(),
        1.5,
        -2.25,
        (0, 0, 0.7071, 0.7071),
        55.5,
        charging=True,
        loaded=False,
        path=[(1, 2), (3.5, 4)],
    )
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
    result = decode_coordinates("blabla", pose_json(status=DROP), NOW, Limits())
    assert isinstance(result, Envelope)
    assert (result.payload.battery_level, result.payload.charging, result.payload.loaded) == (
        None,
        None,
        None,
    )


def test_encode_chunk_create_round_trips() -> None:
    """What encode_chunk_create writes, decode_chunk_create accepts with the same pixels."""
    pixels = bytes(i % 251 for i in range(10_000))
    result = decode_chunk_create(
        encode_chunk_create(7, 9, pixels, stamp(-1000), "rx"), NOW, Limits()
    )
    assert isinstance(result, Envelope)
    assert zlib.decompress(result.payload.data) == pixels
    assert (result.payload.row, result.payload.column, result.event_time_ms) == (7, 9, NOW - 1000)


@pytest.mark.parametrize(
    "text,expected",
    [
        ("2026-11-21T10:00:00", NOW),
        ("2026-11-21T10:00:00Z", NOW),
        ("2026-11-21T10:00:00+00:00", NOW),
        ("2026-11-21T11:30:00+01:30", NOW),
        ("2026-11-21T10:00:00.250", NOW + 250),
    ],
)
def test_timestamp_without_zone_is_utc(text: str, expected: int) -> None:
    """A timestamp without a zone means UTC; explicit offsets are honoured."""
    assert parse_timestamp(text) == expected


def test_pose_timestamp_without_zone_is_utc() -> None:
    """A zoneless message timestamp is stored as the same instant as its UTC spelling."""
    plain = decode_coordinates("blabla", pose_json(timestamp="2026-11-21T09:59:00"), NOW, Limits())
    zoned = decode_coordinates(
        "blabla", pose_json(timestamp="2026-11-21T10:59:00+01:00"), NOW, Limits()
    )
    assert plain.event_time_ms == zoned.event_time_ms == NOW - 60_000


@pytest.mark.parametrize(
    "ms,text", [(NOW, "2026-11-21T10:00:00"), (NOW + 5, "2026-11-21T10:00:00.005")]
)
def test_format_timestamp_is_2019_style(ms: int, text: str) -> None:
    """format_timestamp writes the 2019 style (no zone, milliseconds only when needed)."""
    assert format_timestamp(ms) == text
    assert parse_timestamp(text) == ms


@settings(max_examples=200, deadline=None, database=None)
@given(
    ms=st.lists(st.integers(-(10**12), 4 * 10**12) | st.integers(0, 10**6).map(lambda s: s * 1000))
)
def test_format_timestamps_equals_format_timestamp(ms: list[int]) -> None:
    """format_timestamps (vectorised, for whole maps) writes exactly what format_timestamp does."""
    assert format_timestamps(ms) == [format_timestamp(m) for m in ms]


@pytest.mark.parametrize(
    "field,value",
    [
        ("charging", "x" * 120_000),
        ("loaded", "y" * 65),
        ("timestamp", "2" * 65),
        ("robotId", "r" * 300),
    ],
)
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
    samples = [
        0,
        -1,
        59_999,
        60_000,
        1_763_911_229_435,
        1_763_911_229_000,
        -62_135_596_800_000,
        253_402_300_799_000,
    ] + [rng.randrange(-(10**12), 4 * 10**12) for _ in range(5000)]
    for ms in samples:
        assert format_timestamp(ms) == _format_timestamp_datetime(ms), ms
    assert format_timestamp(1_763_911_229_435.0) == "2025-11-23T15:20:29.435"
