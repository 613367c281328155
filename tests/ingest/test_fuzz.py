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
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.adapters.clock import ManualClock
from mapservice.core.events import decode, decode_dead_letter
from mapservice.core.wire2019 import (
    _ROBOT_ID,
    Reason,
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
)
from mapservice.ingest.gateway import Ingestor
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher

NOW = 1_795_255_200_000
BUDGET = settings(
    max_examples=10_000,
    deadline=None,
    derandomize=True,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.filter_too_much,
    ],
)
REASONS = {r.value for r in Reason}

json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=False, allow_infinity=False),
    st.text(max_size=50),
    st.just("x" * 70_000),
    st.sampled_from(
        [
            "",
            "true",
            "NaN",
            "1e309",
            "\u0000",
            "\udcff".encode("utf-8", "surrogatepass").decode("utf-8", "replace"),
        ]
    ),
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=10), inner, max_size=4)
    ),
    max_leaves=12,
)


def good_chunk(ts: int = NOW, pixels: bytes = bytes(100 * 100)) -> dict:
    return json.loads(encode_chunk_create(1, 2, pixels, format_timestamp(ts), "fuzz-1"))


def good_pose(ts: int = NOW) -> dict:
    """At (1.0, 2.0) with battery 50: raw_nasties replaces those numbers in its text."""
    return json.loads(
        encode_coordinates("fuzz-1", format_timestamp(ts), 1.0, 2.0, battery_level=50)
    )


def mutate(doc: dict, draw) -> dict:
    """Replace, drop or add fields anywhere in the document."""
    doc = json.loads(json.dumps(doc))
    for _ in range(draw(st.integers(1, 4))):
        path, node = [], doc
        while isinstance(node, dict) and node and draw(st.booleans()):
            key = draw(st.sampled_from(sorted(node)))
            path.append(key)
            if not isinstance(node[key], dict):
                break
            node = node[key]
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["replace", "drop", "add"]))
        if not path or action == "add":
            parent[draw(st.text(max_size=8))] = draw(json_values)
        elif action == "drop":
            parent.pop(path[-1], None)
        else:
            parent[path[-1]] = draw(json_values)
    return doc


def raw_nasties(good: dict) -> st.SearchStrategy[bytes]:
    text = json.dumps(good)
    return st.one_of(
        st.binary(max_size=300),  # mostly invalid UTF-8 / not JSON
        st.integers(1, 5000).map(lambda n: b'{"x":' + b"[" * n + b"]" * n + b"}"),  # deep nesting
        st.integers(0, len(text)).map(lambda n: text[:n].encode()),  # truncated
        st.sampled_from(
            [
                text.replace("1.0", "NaN"),
                text.replace("1.0", "Infinity"),
                text.replace("1.0", "1e999"),
                text.replace("50", "-1e-400"),
            ]
        ).map(str.encode),
        st.just(b"{" + b'"a":1,' * 60_000 + b'"b":2}'),  # over the size limit
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
def handler():
    settings_ = Settings()
    publisher = MemoryPublisher()
    ingestor = Ingestor(settings_, publisher, ManualClock(NOW), gateway_id="fuzz")
    return ingestor, publisher, settings_


def handle_and_check(handler, topic: str, payload: bytes) -> None:
    ingestor, publisher, s = handler
    acked = []
    record = ingestor.handle(topic, payload, lambda: acked.append(1))
    publisher.poll()
    assert acked == [1], "every message is acknowledged once Kafka has its record"
    assert ingestor.in_flight == 0
    if record.reason is None:
        envelope = decode(record.value)
        # A mutation may name another valid robot in a chunk; a pose must match its topic.
        assert _ROBOT_ID.fullmatch(envelope.robot_id)
        if topic.startswith("iot/coordinates/"):
            assert envelope.robot_id == topic.rsplit("/", 1)[1]
    else:
        assert record.topic == s.topic_dead_letter and record.reason in REASONS
        letter = decode_dead_letter(record.value)
        assert letter.reason == record.reason and len(letter.payload) <= 64 * 1024


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
    ingestor, publisher, _ = handler
    for topic, doc in (
        ("iot/chunks/create", good_chunk()),
        ("iot/coordinates/fuzz-1", good_pose()),
    ):
        record = ingestor.handle(topic, json.dumps(doc).encode(), lambda: None)
        publisher.poll()
        assert record.reason is None, (topic, record.reason)
