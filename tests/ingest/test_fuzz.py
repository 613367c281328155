"""Property-based fuzzing of every MQTT payload type through the gateway's message handler
(`Ingestor.handle`: routing, 2019 validation, dead letters, the producer contract), with a
fixed budget of 10,000 generated messages per type: wrong types, NaN/Infinity, huge and
tiny numbers, deep nesting, long and odd strings, invalid UTF-8, zlib bombs, over-size
messages. Each must end as an accepted event or a dead letter with a known reason, be
acknowledged, and leave the handler working (a good message after it is accepted).

What this does not cover: the MQTT broker and Kafka themselves (the message handler runs
in-process with the in-memory publisher); tests/integration/test_poison_messages.py sends
the nastiest cases through Mosquitto, the gateway process and Apache Kafka."""

from __future__ import annotations

import base64
import json
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

BUDGET = budget(10_000)


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


@st.composite
def chunk_payloads(draw) -> bytes:
    kind = draw(st.sampled_from(["mutated", "raw", "pixels"]))
    if kind == "mutated":
        return json.dumps(mutate(good_chunk(), draw)).encode()
    if kind == "raw":
        return draw(raw_nasties(good_chunk()))
    # Odd pixel data: wrong sizes, zlib bombs, bad base64, corrupt zlib.
    if draw(st.booleans()):
        data = draw(st.sampled_from(ODD_PIXELS))
    else:  # corrupt: a valid stream cut short
        data = base64.b64encode(
            zlib.compress(draw(st.binary(min_size=100, max_size=2000)) * 5)
        ).decode()[:-8]
    return json.dumps({**good_chunk(), "pgmB64compressedData": data}).encode()


@st.composite
def pose_payloads(draw) -> bytes:
    if draw(st.booleans()):
        return json.dumps(mutate(good_pose(), draw)).encode()
    return draw(raw_nasties(good_pose()))


# Thousands of "message rejected" info lines would cost more than the handling.
pytestmark = pytest.mark.usefixtures("quiet_rejection_logs")


@pytest.fixture(scope="module")
def handler() -> FuzzedGateway:
    return FuzzedGateway("fuzz")


def handle_and_check(handler: FuzzedGateway, topic: str, payload: bytes) -> None:
    event = handler.fate(topic, payload).event
    if event is not None:
        # A mutation may name another valid robot in a chunk; a pose must match its topic.
        assert _ROBOT_ID.fullmatch(event.robot_id)
        if topic.startswith("iot/coordinates/"):
            assert event.robot_id == topic.rsplit("/", 1)[1]


@BUDGET
@given(payload=chunk_payloads())
def test_chunk_create_messages_never_break_the_gateway(handler, payload) -> None:
    """10,000 generated iot/chunks/create payloads: accepted or dead-lettered with a reason."""
    handle_and_check(handler, "iot/chunks/create", payload)


@BUDGET
@given(payload=pose_payloads())
def test_coordinate_messages_never_break_the_gateway(handler, payload) -> None:
    """10,000 generated iot/coordinates/<robot> payloads: accepted or dead-lettered with a reason."""
    handle_and_check(handler, "iot/coordinates/fuzz-1", payload)


def test_after_the_fuzzing_good_messages_are_accepted(handler) -> None:
    """The handler still accepts a good chunk and pose after everything above."""
    for topic, doc in (
        ("iot/chunks/create", good_chunk()),
        ("iot/coordinates/fuzz-1", good_pose()),
    ):
        fate = handler.fate(topic, json.dumps(doc).encode())
        assert fate.reason is None, (topic, fate.letter)
