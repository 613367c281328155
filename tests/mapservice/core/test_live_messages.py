"""Live stream messages (pure): their shapes and their live-topic records."""

from __future__ import annotations

import msgspec
import pytest

from mapservice.core.live_messages import (
    BadLiveRecord,
    decode_live_record,
    live_message,
    live_records,
)


def test_live_message_shapes(ev):
    """Poses and chunks become typed JSON messages; meta events are not streamed."""
    pose = live_message(ev.pose("r1", 1_000, x=1.5))
    assert pose["type"] == "pose" and pose["position"][0] == 1.5 and pose["robotId"] == "r1"
    chunk = live_message(ev.chunk("r2", 2_000, 3, 4))
    assert chunk["type"] == "chunk" and (chunk["row"], chunk["column"]) == (3, 4)
    assert len(chunk["content_hash"]) == 32
    assert live_message(ev.meta(3_000)) is None


def test_live_records_round_trip_the_messages_in_order(ev):
    """A batch's records decode to exactly its live messages, in order, meta left out."""
    events = [
        ev.pose("r1", 1_000),
        ev.meta(1_500),
        ev.chunk("r2", 2_000, 3, 4),
        ev.pose("r1", 3_000),
    ]
    records = live_records(events)
    assert len(records) == 1
    assert decode_live_record(records[0]) == [
        msgspec.json.decode(msgspec.json.encode(live_message(e)))
        for e in events
        if live_message(e) is not None
    ]
    assert live_records([ev.meta(1)]) == []


def test_live_records_are_cut_below_the_size_limit(ev):
    """A large batch becomes several records of at most max_bytes, nothing lost."""
    events = [ev.pose(f"r{i}", 1_000 + i) for i in range(200)]
    records = live_records(events, max_bytes=4_000)
    assert len(records) > 1 and all(len(r) <= 4_000 for r in records)
    decoded = [m for r in records for m in decode_live_record(r)]
    assert [(m["robotId"], m["ts_ms"]) for m in decoded] == [
        (f"r{i}", 1_000 + i) for i in range(200)
    ]


@pytest.mark.parametrize(
    "value", [b"", b"not json", b'{"type": "pose"}', b'[{"type": "meta"}]', b"[1]"]
)
def test_bad_live_records_are_refused(value):
    """A live-topic record that is not an array of pose/chunk messages raises BadLiveRecord."""
    with pytest.raises(BadLiveRecord):
        decode_live_record(value)


def test_live_records_are_byte_for_byte_the_json_of_live_message(ev):
    """The struct encoding of a batch is exactly the JSON of `live_message`'s dicts, with
    and without a planned path, for chunks too."""
    import msgspec as ms

    events = [ev.pose("r1", 1_000, x=1.5), ev.chunk("r2", 2_001, 3, 4), ev.pose("r3", 3_000)]
    with_path = events[0].payload.__class__(
        **{
            **{f: getattr(events[0].payload, f) for f in events[0].payload.__struct_fields__},
            "path": ((1.0, 2.0), (3.5, -4.0)),
        }
    )
    events.append(ms.structs.replace(events[0], payload=with_path))
    expected = b"[" + b",".join(ms.json.encode(live_message(e)) for e in events) + b"]"
    assert live_records(events) == [expected]


def test_live_record_texts_read_as_the_decoded_messages_and_add_sent_ms(ev):
    """Each message kept as text reads like decode_live_record's dict, and with_sent_ms is
    that message's JSON plus sent_ms."""
    from mapservice.core.live_messages import live_record_texts

    record = live_records([ev.pose("r1", 1_000, x=2.5), ev.chunk("r2", 2_000, 3, 4)])[0]
    texts = live_record_texts(record)
    assert [dict(t) for t in texts] == decode_live_record(record)
    assert msgspec.json.decode(texts[0].with_sent_ms(1234)) == {
        **decode_live_record(record)[0],
        "sent_ms": 1234,
    }


@pytest.mark.parametrize(
    "value",
    [b"", b"not json", b'{"type": "pose"}', b'[{"type": "meta"}]', b"[1]", b'[{"type": 5}]'],
)
def test_live_record_texts_refuse_what_decode_live_record_refuses(value):
    """The text path refuses the same bad records with BadLiveRecord."""
    from mapservice.core.live_messages import live_record_texts

    with pytest.raises(BadLiveRecord):
        live_record_texts(value)
