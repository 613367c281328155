"""Live stream messages (pure): their shapes and their live-topic records."""

from __future__ import annotations

import msgspec
import pytest

from mapservice.core.live_messages import BadLiveRecord, live_record_texts, live_records


def messages_of(records: list[bytes]) -> list[dict]:
    """The live messages of some records, as the API reads them (LiveText, as mappings)."""
    return [dict(text) for record in records for text in live_record_texts(record)]


def test_live_message_shapes(ev):
    """Poses and chunks become typed JSON messages, field for field in this order (a
    planned path as [x, y] pairs); meta events are not streamed."""
    pose = ev.pose("r1", 1_000, x=1.5, path=((1.0, 2.0), (3.5, -4.0)))
    chunk = ev.chunk("r2", 2_001, 3, 4)
    records = live_records([pose, ev.meta(1_500), chunk, ev.pose("r3", 3_000)])
    common = ("robotId", "ts_ms", "timestamp", "receive_time_ms")
    expected = [
        {
            "type": "pose",
            **dict(zip(common, ("r1", 1_000, "1970-01-01T00:00:01", 1_040), strict=True)),
            "position": [1.5, 2.0, 0.0],
            "orientation": [0.0, 0.0, 0.0, 1.0],
            "battery_level": 80.0,
            "charging": None,
            "loaded": None,
            "path": [[1.0, 2.0], [3.5, -4.0]],
        },
        {
            "type": "chunk",
            **dict(zip(common, ("r2", 2_001, "1970-01-01T00:00:02.001", 2_026), strict=True)),
            "row": 3,
            "column": 4,
            "content_hash": chunk.payload.content_hash.hex(),
        },
    ]
    got = messages_of(records)
    assert got[:2] == expected and [list(m) for m in got[:2]] == [list(m) for m in expected]
    assert got[2]["path"] is None and len(got) == 3
    # The record is the messages' compact JSON, nothing around or between them.
    assert records[0].startswith(b"[" + msgspec.json.encode(expected[0]) + b",")


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
    assert [(m["type"], m["robotId"], m["ts_ms"]) for m in messages_of(records)] == [
        ("pose", "r1", 1_000),
        ("chunk", "r2", 2_000),
        ("pose", "r1", 3_000),
    ]
    assert live_records([ev.meta(1)]) == []


def test_live_records_are_cut_below_the_size_limit(ev):
    """A large batch becomes several records of at most max_bytes, nothing lost."""
    events = [ev.pose(f"r{i}", 1_000 + i) for i in range(200)]
    records = live_records(events, max_bytes=4_000)
    assert len(records) > 1 and all(len(r) <= 4_000 for r in records)
    assert [(m["robotId"], m["ts_ms"]) for m in messages_of(records)] == [
        (f"r{i}", 1_000 + i) for i in range(200)
    ]


@pytest.mark.parametrize(
    "value",
    [b"", b"not json", b'{"type": "pose"}', b'[{"type": "meta"}]', b"[1]", b'[{"type": 5}]'],
)
def test_bad_live_records_are_refused(value):
    """A live-topic record that is not an array of pose/chunk messages raises BadLiveRecord."""
    with pytest.raises(BadLiveRecord):
        live_record_texts(value)


def test_live_record_texts_read_as_the_decoded_messages_and_add_sent_ms(ev):
    """Each message kept as text reads like the record's decoded JSON, and with_sent_ms is
    that message's JSON plus sent_ms."""
    record = live_records([ev.pose("r1", 1_000, x=2.5), ev.chunk("r2", 2_000, 3, 4)])[0]
    texts = live_record_texts(record)
    assert [dict(t) for t in texts] == msgspec.json.decode(record)
    assert msgspec.json.decode(texts[0].with_sent_ms(1234)) == {
        **msgspec.json.decode(record)[0],
        "sent_ms": 1234,
    }
