"""The API's live fan-out: the hub drops a slow subscriber's oldest messages, and the
WebSocket streams what the hub publishes or says why it cannot."""

from __future__ import annotations

import asyncio
from contextlib import contextmanager

from fastapi.testclient import TestClient

from mapservice.api.app import create_app
from mapservice.api.live_hub import LiveHub
from mapservice.core.live_messages import LiveText, live_record_texts, live_records
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

# The live stream answers only the service's own host names; the test client's default
# Host, "testserver", is not one.
LIVE_URL = "ws://localhost/api/v1/live"


def live_texts(events) -> list[LiveText]:
    """The events' live messages as the relay hands them to the hub (encoded by the
    processors' encoder, read back from the live topic's records)."""
    return [text for record in live_records(events) for text in live_record_texts(record)]


def test_slow_subscriber_keeps_the_newest(ev):
    """A full queue drops its oldest message, never blocks the publisher."""
    hub = LiveHub(queue_size=2)
    queue = hub.subscribe()
    hub.publish(live_texts([ev.pose("r1", t) for t in (1, 2, 3)]))
    assert [queue.get_nowait()["ts_ms"] for _ in range(2)] == [2, 3]
    hub.unsubscribe(queue)
    assert hub.subscribers == 0


def test_the_processes_own_feeds_get_every_message_but_are_no_viewers(ev):
    """A feed of the process (the Foxglove server's) gets what viewers get, and the cap on
    viewers (MAPSERVICE_API_MAX_LIVE_CLIENTS) counts only the viewers, however many of each."""
    for feeds, viewers in ((1, 0), (1, 3), (2, 1), (0, 2)):
        hub = LiveHub()
        queues = [hub.subscribe(viewer=False) for _ in range(feeds)]
        queues += [hub.subscribe() for _ in range(viewers)]
        assert hub.subscribers == viewers
        hub.publish(live_texts([ev.pose("r1", 5)]))
        assert all(q.get_nowait()["ts_ms"] == 5 for q in queues)
        for q in queues:
            hub.unsubscribe(q)
        assert hub.subscribers == 0


def test_websocket_streams_published_messages(ev):
    """/api/v1/live delivers what the relay hands the hub after the client connected."""
    hub = LiveHub()
    with viewer(hub) as (client, ws):
        other = hub.subscribe()  # a second viewer that has not sent its copy yet
        # The hub lives on the app's loop; the relay hands it messages there too.
        client.portal.call(lambda: hub.publish(live_texts([ev.pose("r9", 5_000, x=2.0)])))
        message = ws.receive_json()
    assert message["type"] == "pose" and message["robotId"] == "r9" and "sent_ms" in message
    assert "sent_ms" not in other.get_nowait()  # each viewer stamps its own send time


def test_websocket_without_a_live_feed_closes_with_reason():
    """An API built without a live feed says so (1011) instead of hanging."""
    client = TestClient(create_app(Settings(), MemoryStore(), {}))
    with client.websocket_connect(LIVE_URL) as ws:
        closed = ws.receive()
    assert closed["type"] == "websocket.close" and closed["code"] == 1011


def test_websocket_before_the_feed_is_ready_asks_to_retry():
    """Until the relay reads the live topic, /api/v1/live closes with 1013 (try again later)."""
    client = TestClient(
        create_app(Settings(), MemoryStore(), {}, live_hub=LiveHub(ready=lambda: False))
    )
    with client.websocket_connect(LIVE_URL) as ws:
        closed = ws.receive()
    assert closed["type"] == "websocket.close" and closed["code"] == 1013
    assert "Kafka" in closed["reason"]


def test_websocket_sends_a_live_text_as_it_came_with_its_send_time(ev):
    """A message the relay kept as JSON text goes out as that text plus sent_ms."""
    hub = LiveHub()
    texts = live_texts([ev.pose("r7", 6_000, x=3.0)])
    with viewer(hub) as (client, ws):
        client.portal.call(lambda: hub.publish(texts))
        raw = ws.receive_text()
    assert raw.startswith(texts[0].text[:-1] + ',"sent_ms":')
    assert ws_json(raw)["robotId"] == "r7" and isinstance(ws_json(raw)["sent_ms"], int)


def test_batched_frames_carry_several_events_in_order_each_with_sent_ms(ev):
    """With ?batch=true what queued up arrives as one JSON array, in order, each event with its sent_ms."""
    hub = LiveHub()
    texts = live_texts([ev.pose("r1", 1_000), ev.chunk("r1", 2_000), ev.pose("r2", 3_000)])
    queued = [texts[0], texts[2], texts[1]]
    with viewer(hub, "?batch=true") as (client, ws):
        client.portal.call(lambda: hub.publish(queued))
        frame = ws.receive_json()
    assert isinstance(frame, list) and len(frame) == 3
    assert [(m["type"], m["robotId"], m["ts_ms"]) for m in frame] == [
        ("pose", "r1", 1_000),
        ("pose", "r2", 3_000),
        ("chunk", "r1", 2_000),
    ]
    assert all(isinstance(m["sent_ms"], int) for m in frame)
    assert {k: v for k, v in frame[1].items() if k != "sent_ms"} == dict(queued[1])


def test_batched_frames_hold_at_most_1000_events(ev):
    """1,500 events queued while the client is not reading arrive in frames of at most 1,000, all in order."""
    hub = LiveHub()
    messages = live_texts([ev.pose("r1", t) for t in range(1, 1_501)])
    with viewer(hub, "?batch=true") as (client, ws):
        client.portal.call(lambda: hub.publish(messages))
        frames = [ws.receive_json()]
        while sum(map(len, frames)) < 1_500:
            frames.append(ws.receive_json())
    assert max(map(len, frames)) == 1_000
    assert [m["ts_ms"] for frame in frames for m in frame] == list(range(1, 1_501))


def test_unbatched_stream_sends_one_event_per_message(ev):
    """Without batch (and with batch=false) each message is one JSON object, as before batching existed."""
    hub = LiveHub()
    for query in ("", "?batch=false"):
        with viewer(hub, query) as (client, ws):
            client.portal.call(lambda: hub.publish(live_texts([ev.pose("r1", t) for t in (1, 2)])))
            got = [ws.receive_json(), ws.receive_json()]
        assert [(type(m), m["ts_ms"]) for m in got] == [(dict, 1), (dict, 2)]
        assert all("sent_ms" in m for m in got)


def test_a_bad_batch_value_is_refused_with_a_reason():
    """?batch=maybe is accepted, then closed with 1008 and a reason naming the parameter."""
    client = TestClient(create_app(Settings(), MemoryStore(), {}, live_hub=LiveHub()))
    # Accepted first: a close before accept reaches a real client as a bare HTTP 403.
    with client.websocket_connect(LIVE_URL + "?batch=maybe") as ws:
        closed = ws.receive()
    assert closed["type"] == "websocket.close" and closed["code"] == 1008
    assert closed["reason"] == "query parameter batch must be true or false, not 'maybe'"


@contextmanager
def viewer(hub: LiveHub, query: str = ""):
    """An app on `hub` and a WebSocket on /api/v1/live (plus `query`), once the hub counts it."""
    with (
        TestClient(create_app(Settings(), MemoryStore(), {}, live_hub=hub)) as client,
        client.websocket_connect(LIVE_URL + query) as ws,
    ):
        for _ in range(100):
            if hub.subscribers:
                break
            asyncio.run(asyncio.sleep(0.01))
        yield client, ws


def ws_json(text: str) -> dict:
    import json

    return json.loads(text)
