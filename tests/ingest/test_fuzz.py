"""Property-based fuzzing of every MQTT payload type through the gateway's message handler
(`Ingestor.handle`: routing, 2019 validation, dead letters, the producer contract), with a
fixed budget of 2,500 generated messages per type (`MAPSERVICE_FUZZ_2019_EXAMPLES` to
change it): wrong types, NaN/Infinity, huge and tiny numbers, deep nesting, long and odd
strings, invalid UTF-8, zlib bombs, over-size messages, other robots' names. Each must end
as an accepted event or a dead letter with a known reason, be acknowledged, and leave the
handler working (a good message after it is accepted). The budget must reach every class
of bad input the generators aim at (each test checks that every one was met). With the
near misses generated on purpose, in a run of the generators alone each class turned up
within the first 125 messages and most dozens of times: the budget is there for the
variety within a class, not to find one (a message costs Hypothesis about 4 ms to
generate, the handler under 1 ms).

What this does not cover: the MQTT broker and Kafka themselves (the message handler runs
in-process with the in-memory publisher); tests/integration/test_poison_messages.py sends
the nastiest cases through Mosquitto, the gateway process and Apache Kafka."""

from __future__ import annotations

import base64
import json
import os
import zlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.core.wire2019 import (
    _ROBOT_ID,
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
)
from tests.ingest.fuzz_kit import NOW, FuzzedGateway, budget, mutate, raw_nasties

BUDGET = budget(int(os.environ.get("MAPSERVICE_FUZZ_2019_EXAMPLES", "2500")))


def good_chunk(ts: int = NOW, pixels: bytes = bytes(100 * 100)) -> dict:
    return json.loads(encode_chunk_create(1, 2, pixels, format_timestamp(ts), "fuzz-1"))


def good_pose(ts: int = NOW) -> dict:
    """At (1.0, 2.0) with battery 50: raw_nasties replaces those numbers in its text."""
    return json.loads(
        encode_coordinates("fuzz-1", format_timestamp(ts), 1.0, 2.0, battery_level=50)
    )


# Built once: compressing 50 MB takes a tenth of a second.
ZLIB_BOMB = base64.b64encode(zlib.compress(bytes(50_000_000))).decode()  # 50 MB in ~49 KB
ODD_PIXELS = [
    ZLIB_BOMB,
    base64.b64encode(zlib.compress(bytes(99))).decode(),
    "!!!not base64!!!",
    base64.b64encode(b"not zlib").decode(),
]


# The good messages the payloads are made from, built once (a chunk's pixels are compressed
# and encoded) and only ever copied: the cost of a generated message is its generation.
GOOD_CHUNK = good_chunk()
GOOD_POSE = good_pose()
ODD_PIXEL_DATA = st.one_of(
    *map(st.just, ODD_PIXELS),
    st.binary(min_size=100, max_size=2000).map(  # a valid stream cut short
        lambda data: base64.b64encode(zlib.compress(data * 5)).decode()[:-8]
    ),
)


# A field set to a value of its own kind gone wrong: another robot's name (on fuzz-1's
# topic, for a pose) or no name at all, a timestamp that does not parse or is years off, a
# cell or a position far off. Mutations seldom make these: a random value is mostly of the
# wrong type.
ROBOT_NAMES = st.one_of(st.from_regex(_ROBOT_ID, fullmatch=True), st.text(max_size=70))
TIMESTAMPS = st.one_of(
    st.text(max_size=30),
    st.integers(0, NOW).map(format_timestamp),  # mostly too old
    st.integers(NOW, 2**41).map(format_timestamp),  # mostly in the future
)
COMMON_NEAR_MISSES = [
    st.tuples(st.just(("robotId",)), ROBOT_NAMES),
    st.tuples(st.just(("timestamp",)), TIMESTAMPS),
]
CHUNK_NEAR_MISSES = st.one_of(
    *COMMON_NEAR_MISSES,
    st.tuples(st.sampled_from([("row",), ("column",)]), st.integers(-(2**40), 2**40)),
)
POSE_NEAR_MISSES = st.one_of(
    *COMMON_NEAR_MISSES,
    st.tuples(st.just(("pose", "position", "x")), st.floats(allow_nan=False)),
)


def near_miss(good: dict, path: tuple[str, ...], value) -> bytes:
    doc = json.loads(json.dumps(good))
    *parents, name = path
    node = doc
    for key in parents:
        node = node[key]
    node[name] = value
    return json.dumps(doc).encode()


CHUNK_KINDS = st.sampled_from(["mutated", "raw", "pixels", "near miss"])
POSE_KINDS = st.sampled_from(["mutated", "raw", "near miss"])


@st.composite
def chunk_payloads(draw) -> bytes:
    kind = draw(CHUNK_KINDS)
    if kind == "mutated":
        return json.dumps(mutate(GOOD_CHUNK, draw)).encode()
    if kind == "raw":
        return draw(raw_nasties(GOOD_CHUNK))
    if kind == "near miss":
        return near_miss(GOOD_CHUNK, *draw(CHUNK_NEAR_MISSES))
    # Odd pixel data: wrong sizes, zlib bombs, bad base64, corrupt zlib.
    data = draw(ODD_PIXEL_DATA)
    return json.dumps({**GOOD_CHUNK, "pgmB64compressedData": data}).encode()


@st.composite
def pose_payloads(draw) -> bytes:
    kind = draw(POSE_KINDS)
    if kind == "mutated":
        return json.dumps(mutate(GOOD_POSE, draw)).encode()
    if kind == "raw":
        return draw(raw_nasties(GOOD_POSE))
    return near_miss(GOOD_POSE, *draw(POSE_NEAR_MISSES))


# Thousands of "message rejected" info lines would cost more than the handling.
pytestmark = pytest.mark.usefixtures("quiet_rejection_logs")


@pytest.fixture(scope="module")
def handler() -> FuzzedGateway:
    return FuzzedGateway("fuzz")


def handle_and_check(handler: FuzzedGateway, topic: str, payload: bytes) -> str:
    """What became of the message: "accepted" or its dead letter's reason."""
    fate = handler.fate(topic, payload)
    if fate.event is not None:
        # A mutation may name another valid robot in a chunk; a pose must match its topic.
        assert _ROBOT_ID.fullmatch(fate.event.robot_id)
        if topic.startswith("iot/coordinates/"):
            assert fate.event.robot_id == topic.rsplit("/", 1)[1]
    return fate.reason or "accepted"


def fuzz(handler: FuzzedGateway, topic: str, payloads: st.SearchStrategy[bytes]) -> set[str]:
    """Every generated payload handled and checked; what became of them, all told."""
    outcomes: set[str] = set()

    @BUDGET
    @given(payload=payloads)
    def each(payload: bytes) -> None:
        outcomes.add(handle_and_check(handler, topic, payload))

    each()
    return outcomes


# What the generators aim at, each a class of bad input (or none): the budget must reach
# every one, so a budget too small for a class (or a generator that lost one) fails here.
CHUNK_OUTCOMES = {
    "accepted", "oversized", "not_json", "missing_field", "wrong_type", "too_deep",
    "bad_robot_id", "bad_timestamp", "timestamp_in_future", "timestamp_too_old",
    "out_of_map", "bad_base64", "bad_zlib", "wrong_chunk_size",
}  # fmt: skip
POSE_OUTCOMES = {
    "accepted", "oversized", "not_json", "missing_field", "wrong_type", "too_deep",
    "bad_robot_id", "bad_timestamp", "timestamp_in_future", "timestamp_too_old",
    "robot_id_mismatch", "out_of_range",
}  # fmt: skip


def test_chunk_create_messages_never_break_the_gateway(handler) -> None:
    """2,500 generated iot/chunks/create payloads: accepted or dead-lettered with a
    reason, and every class of bad chunk among them."""
    assert fuzz(handler, "iot/chunks/create", chunk_payloads()) >= CHUNK_OUTCOMES


def test_coordinate_messages_never_break_the_gateway(handler) -> None:
    """2,500 generated iot/coordinates/<robot> payloads: accepted or dead-lettered
    with a reason, and every class of bad pose among them."""
    assert fuzz(handler, "iot/coordinates/fuzz-1", pose_payloads()) >= POSE_OUTCOMES


def test_after_the_fuzzing_good_messages_are_accepted(handler) -> None:
    """The handler still accepts a good chunk and pose after everything above."""
    for topic, doc in (
        ("iot/chunks/create", good_chunk()),
        ("iot/coordinates/fuzz-1", good_pose()),
    ):
        fate = handler.fate(topic, json.dumps(doc).encode())
        assert fate.reason is None, (topic, fate.letter)
