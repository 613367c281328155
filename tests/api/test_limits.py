"""Bounded input on the API: body limits, replies that never echo large input, WebSocket
origins, and no 5xx from odd paths."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from mapservice.api.app import create_app
from mapservice.api.live_hub import LiveHub
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

# The live stream answers only the service's own host names; the test client's default
# Host, "testserver", is not one.
LIVE_URL = "ws://localhost/api/v1/live"


@pytest.fixture
def client() -> TestClient:
    hub = LiveHub()
    hub.ready = lambda: True
    return TestClient(
        create_app(
            Settings(
                api_max_body_bytes=64 * 1024, api_allowed_origins=["https://dash.example.com"]
            ),
            MemoryStore(),
            live_hub=hub,
        )
    )


def test_a_body_over_the_limit_is_413_before_it_is_read(client) -> None:
    """Declared or streamed, a body past MAPSERVICE_API_MAX_BODY_BYTES gets 413 with the setting's name."""
    big = b'{"hashes": ["' + b"a" * 100_000 + b'"]}'
    reply = client.post(
        "/api/v1/chunk-contents/batch", content=big, headers={"content-type": "application/json"}
    )
    assert reply.status_code == 413 and "MAPSERVICE_API_MAX_BODY_BYTES" in reply.json()["detail"]

    def chunks():
        for _ in range(20):
            yield b"x" * 8192

    streamed = client.post(
        "/api/chunk-service/chunks", content=chunks(), headers={"content-type": "application/json"}
    )
    assert streamed.status_code == 413


def test_bodies_within_the_limit_reach_the_route(client) -> None:
    """A normal batch request is answered by its route (here: bad hashes, 400)."""
    reply = client.post("/api/v1/chunk-contents/batch", json={"hashes": ["nothex"]})
    assert reply.status_code == 400 and "nothex" in reply.json()["detail"]


def test_rejected_input_is_never_echoed_at_length(client) -> None:
    """A 50 KB bad value comes back cut to ~200 characters, in 422s and in 400s."""
    reply = client.post("/api/v1/chunk-contents/batch", json={"hashes": ["z" * 50_000]})
    assert reply.status_code == 400 and len(reply.content) < 1000
    wrong_type = client.post("/api/v1/chunk-contents/batch", json={"hashes": "q" * 50_000})
    assert wrong_type.status_code == 422 and len(wrong_type.content) < 1500
    assert "50000 characters" in wrong_type.text


@pytest.mark.parametrize(
    "path", ["/assets/%00", "/assets/..%2f..%2fetc%2fpasswd", "/assets/" + "a" * 5000]
)
def test_odd_asset_paths_are_404_not_500(client, path) -> None:
    """NUL bytes, traversal and long names: 404, never a 5xx."""
    reply = client.get(path)
    assert reply.status_code == 404 and len(reply.content) < 1000


def test_live_refuses_pages_of_other_sites(client) -> None:
    """A browser page from another origin cannot open /api/v1/live; our host, a configured
    origin and non-browser clients (no Origin) can."""
    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect(LIVE_URL, headers={"origin": "https://evil.example"}) as ws:
            ws.receive_json()
    assert refused.value.code == 1008
    for headers in ({"origin": "http://localhost"}, {"origin": "https://dash.example.com"}, {}):
        with client.websocket_connect(LIVE_URL, headers=headers) as ws:
            ws.close()


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8080", "127.0.0.1.nip.io"])
def test_the_live_stream_refuses_other_host_names(host) -> None:
    """DNS rebinding: a page of evil.example whose name resolves to this address sends
    Host and Origin of evil.example, which agree; the Host is not one of the service's, so
    the handshake is refused with a reason naming the setting (before anything else: this
    app has no live feed, which would close with 1011 after accepting)."""
    client = TestClient(create_app(Settings(), MemoryStore()))
    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect(
            LIVE_URL, headers={"host": host, "origin": f"http://{host}"}
        ) as ws:
            ws.receive_json()
    assert refused.value.code == 1008 and "MAPSERVICE_API_ALLOWED_HOSTS" in refused.value.reason


@pytest.mark.parametrize(
    "host", ["localhost:8080", "127.0.0.1", "[::1]:8080", "maps.plant.example"]
)
def test_the_live_stream_takes_loopback_and_configured_host_names(host) -> None:
    """The loopback names and MAPSERVICE_API_ALLOWED_HOSTS are the service's own."""
    hub = LiveHub()
    client = TestClient(
        create_app(Settings(api_allowed_hosts=["maps.plant.example"]), MemoryStore(), live_hub=hub)
    )
    with client.websocket_connect(LIVE_URL, headers={"host": host}) as ws:
        ws.close()
