"""Live stream: messages, their live-topic records, and the API's WebSocket fan-out."""

from __future__ import annotations

import asyncio

import msgspec
import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.memory_store import MemoryStore
from mapservice.api.app import create_app
from mapservice.api.live_hub import LiveHub
from mapservice.core.live_messages import BadLiveRecord, decode_live_record, live_message, live_records
from mapservice.settings import Settings


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
    events = [ev.pose("r1", 1_000), ev.meta(1_500), ev.chunk("r2", 2_000, 3, 4), ev.pose("r1", 3_000)]
    records = live_records(events)
    assert len(records) == 1
    assert decode_live_record(records[0]) == [
        msgspec.json.decode(msgspec.json.encode(live_message(e)))
        for e in events if live_message(e) is not None]
    assert live_records([ev.meta(1)]) == []


def test_live_records_are_cut_below_the_size_limit(ev):
    """A large batch becomes several records of at most max_bytes, nothing lost."""
    events = [ev.pose(f"r{i}", 1_000 + i) for i in range(200)]
    records = live_records(events, max_bytes=4_000)
    assert len(records) > 1 and all(len(r) <= 4_000 for r in records)
    decoded = [m for r in records for m in decode_live_record(r)]
    assert [(m["robotId"], m["ts_ms"]) for m in decoded] == [(f"r{i}", 1_000 + i) for i in range(200)]


@pytest.mark.parametrize("value", [b"", b"not json", b'{"type": "pose"}', b'[{"type": "meta"}]', b"[1]"])
def test_bad_live_records_are_refused(value):
    """A live-topic record that is not an array of pose/chunk messages raises BadLiveRecord."""
    with pytest.raises(BadLiveRecord):
        decode_live_record(value)


def test_slow_subscriber_keeps_the_newest(ev):
    """A full queue drops its oldest message, never blocks the publisher."""
    hub = LiveHub(queue_size=2)
    queue = hub.subscribe()
    hub.publish([live_message(ev.pose("r1", t)) for t in (1, 2, 3)])
    assert [queue.get_nowait()["ts_ms"] for _ in range(2)] == [2, 3]
    hub.unsubscribe(queue)
    assert hub.subscribers == 0


def test_websocket_streams_published_messages(ev):
    """/api/v1/live delivers what the relay hands the hub after the client connected."""
    hub = LiveHub()
    with TestClient(create_app(Settings(), MemoryStore(), {}, live_hub=hub)) as client, \
            client.websocket_connect("/api/v1/live") as ws:
        for _ in range(100):
            if hub.subscribers:
                break
            asyncio.run(asyncio.sleep(0.01))
        other = hub.subscribe()  # a second viewer that has not sent its copy yet
        # The hub lives on the app's loop; the relay hands it messages there too.
        client.portal.call(lambda: hub.publish([live_message(ev.pose("r9", 5_000, x=2.0))]))
        message = ws.receive_json()
    assert message["type"] == "pose" and message["robotId"] == "r9" and "sent_ms" in message
    assert "sent_ms" not in other.get_nowait()  # each viewer stamps its own send time


def test_websocket_without_a_live_feed_closes_with_reason():
    """An API built without a live feed says so (1011) instead of hanging."""
    client = TestClient(create_app(Settings(), MemoryStore(), {}))
    with client.websocket_connect("/api/v1/live") as ws:
        closed = ws.receive()
    assert closed["type"] == "websocket.close" and closed["code"] == 1011


def test_websocket_before_the_feed_is_ready_asks_to_retry():
    """Until the relay reads the live topic, /api/v1/live closes with 1013 (try again later)."""
    client = TestClient(create_app(Settings(), MemoryStore(), {}, live_hub=LiveHub(ready=lambda: False)))
    with client.websocket_connect("/api/v1/live") as ws:
        closed = ws.receive()
    assert closed["type"] == "websocket.close" and closed["code"] == 1013
    assert "Kafka" in closed["reason"]
