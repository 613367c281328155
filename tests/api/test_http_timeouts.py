"""Header, idle and body timeouts of the API as `mapservice api`/`serve` run it (uvicorn with
api/http_timeouts.py), on a real socket: a slowloris connection is closed, normal requests
are not."""

from __future__ import annotations

import socket
import threading
import time

import httpx
import pytest
import uvicorn

from mapservice.api.app import create_app
from mapservice.api.composition import api_server_config
from mapservice.local.embedded import free_port
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

HEADER_S, IDLE_S, BODY_S = 1.0, 1, 1.0
# How late a deadline may fire on a loaded machine (the fast tests run at the lowest CPU
# priority beside others): still far below the defaults a missing setting would leave (30 s).
LATE_S = 4.0


@pytest.fixture(scope="module")
def server():
    """The API on 127.0.0.1 with short timeouts, served by uvicorn in a thread."""
    settings = Settings(
        api_port=free_port(),
        api_header_timeout_s=HEADER_S,
        api_idle_timeout_s=IDLE_S,
        api_body_timeout_s=BODY_S,
        admin_token="a" * 32,
        api_writer_tokens="w" * 32,
    )
    config = api_server_config(create_app(settings, MemoryStore(), {}), settings)
    config.log_level = "warning"
    uv = uvicorn.Server(config)
    thread = threading.Thread(target=uv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not uv.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert uv.started, "uvicorn did not start"
    yield settings
    uv.should_exit = True
    thread.join(10)


def closed_within(sock: socket.socket, seconds: float, trickle: bytes = b"") -> float | None:
    """Seconds until the server closed `sock` (sending `trickle` a byte every 0.2 s meanwhile),
    or None if it was still open after `seconds`."""
    started = time.monotonic()
    sock.settimeout(0.2)
    sent = 0
    while time.monotonic() - started < seconds:
        try:
            if sock.recv(4096) == b"":
                return time.monotonic() - started
        except TimeoutError:
            pass
        except ConnectionResetError:
            return time.monotonic() - started
        if sent < len(trickle):
            try:
                sock.send(trickle[sent : sent + 1])
            except OSError:
                return time.monotonic() - started
            sent += 1
    return None


def healthz_reply(sock: socket.socket) -> bytes:
    """Reads one /healthz response (head and body may come in separate segments)."""
    reply = b""
    while not reply.endswith(b'{"ok":true}'):
        part = sock.recv(4096)
        assert part, f"closed after {reply!r}"
        reply += part
    return reply


def connect(settings: Settings) -> socket.socket:
    return socket.create_connection(("127.0.0.1", settings.api_port), timeout=5)


def test_half_a_request_line_is_closed_after_the_header_timeout(server) -> None:
    """A connection that sends half a request line and then trickles header bytes is closed within the header timeout."""
    with connect(server) as sock:
        sock.sendall(b"GET /healthz HT")
        took = closed_within(
            sock,
            HEADER_S + LATE_S + 2,
            trickle=b"TP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 40,
        )
    assert took is not None and took <= HEADER_S + LATE_S, took


def test_a_normal_request_still_works(server) -> None:
    """A whole request is answered while slow connections wait to be closed."""
    slow = [connect(server) for _ in range(20)]
    try:
        for sock in slow:
            sock.sendall(b"GET /healthz HTTP/1.1\r\n")
        r = httpx.get(f"http://127.0.0.1:{server.api_port}/healthz", timeout=5)
        assert r.status_code == 200 and r.json() == {"ok": True}
    finally:
        for sock in slow:
            sock.close()


def test_an_idle_keep_alive_connection_is_closed(server) -> None:
    """After a response, a connection that sends nothing is closed after the idle timeout."""
    with connect(server) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert b"200 OK" in healthz_reply(sock)
        took = closed_within(sock, IDLE_S + LATE_S + 2)
    assert took is not None and took <= IDLE_S + LATE_S, took


def test_keep_alive_requests_each_get_a_fresh_header_deadline(server) -> None:
    """Several requests on one connection, each well within the deadline, all get answers."""
    with connect(server) as sock:
        for _ in range(3):
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert b"200 OK" in healthz_reply(sock)
            time.sleep(HEADER_S * 0.6)


def test_a_trickled_body_is_refused_after_the_body_timeout(server) -> None:
    """Headers in time but a body that does not come: 408 after MAPSERVICE_API_BODY_TIMEOUT_S."""
    with connect(server) as sock:
        sock.sendall(
            b"POST /api/chunk-service/chunks HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            b"Authorization: Bearer " + b"w" * 32 + b"\r\n"
            b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{"
        )
        sock.settimeout(BODY_S + LATE_S + 2)
        started = time.monotonic()
        reply = sock.recv(4096)
    assert reply.startswith(b"HTTP/1.1 408"), reply[:200]
    assert time.monotonic() - started <= BODY_S + LATE_S
