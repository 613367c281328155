"""Live fan-out: stored events reach every WebSocket subscriber as JSON."""

from __future__ import annotations

import asyncio

from fastapi.testclient import TestClient

from mapservice.adapters.memory_store import MemoryStore
from mapservice.api.app import create_app
from mapservice.live import LiveHub, live_message
from mapservice.settings import Settings


def test_live_message_shapes(ev):
    """Poses and chunks become typed JSON messages; meta events are not streamed."""
    pose = live_message(ev.pose("r1", 1_000, x=1.5))
    assert pose["type"] == "pose" and pose["position"][0] == 1.5 and pose["robotId"] == "r1"
    chunk = live_message(ev.chunk("r2", 2_000, 3, 4))
    assert chunk["type"] == "chunk" and (chunk["row"], chunk["column"]) == (3, 4)
    assert len(chunk["content_hash"]) == 32
    assert live_message(ev.meta(3_000)) is None


def test_slow_subscriber_keeps_the_newest(ev):
    """A full queue drops its oldest message, never blocks the publisher."""
    hub = LiveHub(queue_size=2)
    queue = hub.subscribe()
    hub.publish([ev.pose("r1", t) for t in (1, 2, 3)])
    assert [queue.get_nowait()["ts_ms"] for _ in range(2)] == [2, 3]
    hub.unsubscribe(queue)
    assert hub.subscribers == 0


def test_websocket_streams_published_events(ev):
    """/api/v1/live delivers what the sink publishes after the client connected."""
    hub = LiveHub()
    with TestClient(create_app(Settings(), MemoryStore(), {}, live_hub=hub)) as client, \
            client.websocket_connect("/api/v1/live") as ws:
        for _ in range(100):
            if hub.subscribers:
                break
            asyncio.run(asyncio.sleep(0.01))
        other = hub.subscribe()  # a second viewer that has not sent its copy yet
        # The hub lives on the app's loop; publish from it like the sink does.
        client.portal.call(lambda: hub.publish([ev.pose("r9", 5_000, x=2.0)]))
        message = ws.receive_json()
    assert message["type"] == "pose" and message["robotId"] == "r9" and "sent_ms" in message
    assert "sent_ms" not in other.get_nowait()  # each viewer stamps its own send time


def test_websocket_without_processors_closes_with_reason():
    """An API without in-process processors says so instead of hanging."""
    client = TestClient(create_app(Settings(), MemoryStore(), {}))
    with client.websocket_connect("/api/v1/live") as ws:
        closed = ws.receive()
    assert closed["type"] == "websocket.close" and closed["code"] == 1011
