"""The pure part of the history sink: Kafka values to envelopes or dead letters."""

from __future__ import annotations

import msgspec
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.events import DeadLetter, Envelope, encode, encode_dead_letter
from mapservice.processors.sink import decode_dead_letters, split_events

NOW = 1_795_255_200_000
PROPERTY = settings(
    max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)


def test_good_envelopes_are_decoded_in_order(ev) -> None:
    """Valid envelopes come back equal to what was encoded, in input order, with no dead letters."""
    envelopes = [ev.pose("r1", NOW), ev.chunk("r2", NOW + 1, 3, 4), ev.meta(NOW + 2)]
    events, bad = split_events([encode(e) for e in envelopes], NOW)
    assert events == envelopes
    assert bad == []


def test_garbage_becomes_undecodable_event_dead_letters(ev) -> None:
    """Records that are not envelopes become dead letters with the original bytes; good ones pass."""
    good = ev.pose("r1", NOW)
    garbage = [
        b"",
        b"\xc1",
        b"not msgpack at all",
        msgspec.msgpack.encode({"event_id": "x"}),
        msgspec.msgpack.encode(["id", "pose.reported", 1, "r1", "not-a-time", 0, []]),
        encode_dead_letter(ev.dead_letter()),
    ]  # a dead letter is not an event
    events, bad = split_events([garbage[0], encode(good), *garbage[1:]], NOW + 7)
    assert events == [good]
    assert len(bad) == len(garbage)
    assert [d.payload for d in bad] == garbage
    for letter in bad:
        assert isinstance(letter, DeadLetter)
        assert letter.reason == "undecodable_event"
        assert letter.detail
        assert letter.receive_time_ms == NOW + 7
        assert letter.gateway == "processors"
        assert letter.mqtt_topic == ""


def test_none_value_becomes_a_dead_letter() -> None:
    """A tombstone (None value) is a dead letter with empty payload, not a crash."""
    events, bad = split_events([None], NOW)  # type: ignore[list-item]
    assert events == []
    assert [(d.reason, d.payload) for d in bad] == [("undecodable_event", b"")]


def test_invalid_utf8_string_becomes_a_dead_letter() -> None:
    """A msgpack record whose string is not UTF-8 is a dead letter, not a crash of the sink."""
    poison = b"\x97\xa2\x00\x80"  # array of 7 starting with a 2-byte str that is not UTF-8
    events, bad = split_events([poison], NOW)
    assert events == [] and [(d.reason, d.payload) for d in bad] == [("undecodable_event", poison)]
    (letter,) = decode_dead_letters([b"\x87\xa2\x00\x80"], NOW)
    assert letter.reason == "undecodable_dead_letter"


@PROPERTY
@given(values=st.lists(st.binary(max_size=64), max_size=5))
def test_split_events_never_raises(values: list[bytes]) -> None:
    """Arbitrary bytes are split into events and dead letters, one output per input."""
    events, bad = split_events(values, NOW)
    assert len(events) + len(bad) == len(values)
    assert all(isinstance(e, Envelope) for e in events)
    assert all(d.reason == "undecodable_event" for d in bad)


@PROPERTY
@given(values=st.lists(st.binary(max_size=64), max_size=5))
def test_decode_dead_letters_never_raises(values: list[bytes]) -> None:
    """Arbitrary bytes on the dead-letter topic give one dead letter each, never an exception."""
    assert len(decode_dead_letters(values, NOW)) == len(values)


def test_dead_letters_topic_decodes_and_garbage_is_kept(ev) -> None:
    """Dead-letter records decode; undecodable ones become undecodable_dead_letter records."""
    letter = ev.dead_letter("bad_zlib", b"\x01\x02")
    out = decode_dead_letters([encode_dead_letter(letter), b"\xff\xff"], NOW)
    assert out[0] == letter
    assert (out[1].reason, out[1].payload, out[1].receive_time_ms) == (
        "undecodable_dead_letter",
        b"\xff\xff",
        NOW,
    )
