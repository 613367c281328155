"""Event envelopes: immutability, encoding, natural identity and Kafka keys."""

from __future__ import annotations

import msgspec
import pytest

from mapservice.core.events import (
    SCHEMA_VERSION,
    ChunkUpdated,
    DeadLetter,
    MapMetaSet,
    PoseReported,
    decode,
    decode_dead_letter,
    encode,
    encode_dead_letter,
    event_id_for,
    kafka_key,
    make_envelope,
)

T = 1_795_255_200_000

POSE = PoseReported(
    position=(1.5, -2.25, 0.0),
    orientation=(0.0, 0.0, 0.38268343, 0.92387953),
    battery_level=71.5,
    charging=True,
    loaded="dfs",
    path=((1.0, 2.0), (3.0, 4.5)),
)
CHUNK = ChunkUpdated(
    row=3,
    column=2,
    width=100,
    height=100,
    data=b"x\x9c\x03\x00\x00\x00\x00\x01",
    content_hash=bytes(range(16)),
)
META = MapMetaSet(
    width=1006,
    height=1674,
    chunk_width=100,
    chunk_height=100,
    chunk_rows=17,
    chunk_cols=11,
    comment="warehouse",
    resolution=0.03,
    origin=(-15.1, -25.0, 0.0),
)


@pytest.mark.parametrize("payload", [POSE, CHUNK, META], ids=["pose", "chunk", "meta"])
def test_envelope_and_payload_are_frozen(payload) -> None:
    """Neither an envelope nor its payload can be changed after creation."""
    env = make_envelope("r1", T, T + 5, payload)
    with pytest.raises(AttributeError):
        env.robot_id = "r2"  # type: ignore[misc]
    first_field = payload.__struct_fields__[0]
    with pytest.raises(AttributeError):
        setattr(env.payload, first_field, getattr(payload, first_field))


def test_dead_letter_is_frozen() -> None:
    """A dead letter cannot be changed after creation."""
    letter = DeadLetter("not_json", "x", "iot/chunks/create", b"{", T, "gw")
    with pytest.raises(AttributeError):
        letter.reason = "ok"  # type: ignore[misc]


@pytest.mark.parametrize(
    "payload",
    [POSE, CHUNK, META, PoseReported(position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0))],
    ids=["pose", "chunk", "meta", "bare-pose"],
)
def test_envelope_round_trips(payload) -> None:
    """decode(encode(envelope)) equals the envelope, payload type and all."""
    env = make_envelope("robot-7", T, T + 42, payload)
    back = decode(encode(env))
    assert back == env
    assert type(back.payload) is type(payload)
    assert isinstance(encode(env), bytes)


def test_envelope_fields_are_set_by_make_envelope() -> None:
    """make_envelope fills type, schema version and both clocks."""
    env = make_envelope("r1", T, T + 9, CHUNK)
    assert (env.type, env.version, env.robot_id) == ("chunk.updated", SCHEMA_VERSION, "r1")
    assert (env.event_time_ms, env.receive_time_ms) == (T, T + 9)
    assert make_envelope("r1", T, T, POSE).type == "pose.reported"
    assert make_envelope("r1", T, T, META).type == "map.meta_set"


def test_decode_rejects_a_foreign_payload_type() -> None:
    """An envelope whose payload tag is unknown does not decode."""
    raw = msgspec.msgpack.encode(["id", "x", 1, "r", T, T, ["no.such.tag", 1, 2]])
    with pytest.raises(msgspec.DecodeError):
        decode(raw)


def test_dead_letter_round_trips() -> None:
    """A dead letter keeps the original bytes, reason and topic through encoding."""
    letter = DeadLetter("bad_zlib", "detail", "iot/chunks/create", b"\x00\xffraw", T, "gw-1")
    back = decode_dead_letter(encode_dead_letter(letter))
    assert back == letter
    assert back.version == SCHEMA_VERSION


# --- natural identity ---------------------------------------------------------------------


def test_pose_id_depends_only_on_robot_and_time() -> None:
    """A redelivered pose (same robot and time) gets the same id, whatever else differs."""
    moved = msgspec.structs.replace(POSE, position=(9.0, 9.0, 0.0), battery_level=1.0)
    a = make_envelope("r1", T, T + 1, POSE)
    b = make_envelope("r1", T, T + 5000, moved)
    assert a.event_id == b.event_id
    assert len(a.event_id) == 32 and int(a.event_id, 16) >= 0


@pytest.mark.parametrize("robot,t", [("r2", T), ("r1", T + 1), ("r1", T - 1000)])
def test_pose_id_differs_for_another_robot_or_time(robot: str, t: int) -> None:
    """Poses of another robot or another instant have different ids."""
    assert event_id_for("r1", T, POSE) != event_id_for(robot, t, POSE)


def test_chunk_id_depends_on_chunk_robot_and_time() -> None:
    """A redelivered chunk write (same chunk, robot, time) keeps its id despite other pixels."""
    other_pixels = msgspec.structs.replace(CHUNK, data=b"other", content_hash=bytes(16))
    a = make_envelope("r1", T, T, CHUNK)
    b = make_envelope("r1", T, T + 999, other_pixels)
    assert a.event_id == b.event_id


@pytest.mark.parametrize(
    "change",
    [
        {"row": 4},
        {"column": 3},
        {"robot": "r2"},
        {"t": T + 1},
        {"row": 2, "column": 3},  # swapped row/column must not collide
    ],
)
def test_chunk_id_differs_when_identity_differs(change: dict) -> None:
    """Another chunk, robot or instant gives another id."""
    payload = msgspec.structs.replace(
        CHUNK, row=change.get("row", CHUNK.row), column=change.get("column", CHUNK.column)
    )
    assert event_id_for("r1", T, CHUNK) != event_id_for(
        change.get("robot", "r1"), change.get("t", T), payload
    )


def test_pose_and_chunk_of_same_robot_and_time_have_different_ids() -> None:
    """A pose and a chunk write from one robot at one instant are different events."""
    assert event_id_for("r1", T, POSE) != event_id_for("r1", T, CHUNK)


def test_robot_and_time_are_not_ambiguous_in_the_digest() -> None:
    """("r1", 23...) and ("r12", 3...) do not collide by concatenation."""
    assert event_id_for("r1", 23, POSE) != event_id_for("r12", 3, POSE)


def test_meta_id_depends_on_content() -> None:
    """Two different metas set at one instant by one robot are different events."""
    other = msgspec.structs.replace(META, chunk_rows=18)
    assert event_id_for("admin", T, META) == event_id_for("admin", T, META)
    assert event_id_for("admin", T, META) != event_id_for("admin", T, other)


# --- Kafka keys ---------------------------------------------------------------------------


def test_chunk_key_is_row_colon_column() -> None:
    """Chunk events are keyed by `row:column` so one chunk's writes stay in order."""
    assert kafka_key(make_envelope("r1", T, T, CHUNK)) == b"3:2"
    assert (
        kafka_key(make_envelope("r9", T, T, msgspec.structs.replace(CHUNK, row=12, column=0)))
        == b"12:0"
    )


def test_pose_key_is_robot_id() -> None:
    """Poses are keyed by robot id so one robot's poses stay in order."""
    assert kafka_key(make_envelope("robot-7", T, T, POSE)) == b"robot-7"


def test_meta_key_is_constant() -> None:
    """All metas share one key, so the latest is well defined."""
    assert (
        kafka_key(make_envelope("a", T, T, META))
        == kafka_key(make_envelope("b", T, T, META))
        == b"map"
    )


def test_meta_2019_round_trip() -> None:
    """MapMetaSet survives the 2019 meta.json form, including resolution and origin."""
    doc = META.to_2019()
    assert (
        doc["CHUNK_ROWS"] == 17 and doc["CHUNK_COLS"] == 11 and doc["origin"] == [-15.1, -25.0, 0.0]
    )
    assert MapMetaSet.from_2019(doc) == META
    bare = MapMetaSet(
        width=10, height=10, chunk_width=5, chunk_height=5, chunk_rows=2, chunk_cols=2
    )
    assert "origin" not in bare.to_2019() and MapMetaSet.from_2019(bare.to_2019()) == bare
