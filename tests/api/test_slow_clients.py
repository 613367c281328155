"""Clients that do not read, against a real uvicorn: an export is produced only as fast as
it is read (a few MB ahead at most) and aborted at its deadline; a live client that takes
no message is dropped. In-process ASGI test clients read everything, so these need sockets."""

from __future__ import annotations

import asyncio
import base64
import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import uvicorn
from fastapi.testclient import TestClient

from mapservice.api.app import create_app
from mapservice.api.live_hub import LiveHub
from mapservice.api.routers.exports import write_csv_slices
from mapservice.api.streaming import BoundedPipe, ExportAborted
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

T0 = 1_795_255_200_000
BYTES_PER_MINUTE = 4 * 1024  # of CSV: a 7-day window is ~40 MB


class EndlessCsvStore(MemoryStore):
    """A ClickHouse stand-in whose table export writes BYTES_PER_MINUTE of window: seven
    days are ~40 MB per client if produced at once, as the export did before it streamed."""

    def __init__(self) -> None:
        super().__init__()
        self.database = "db"
        self.queries = 0
        self.produced = 0
        self.lock = threading.Lock()

    def export_query(self, sql: str, parameters: dict, fmt: str) -> bytes:
        minutes = (parameters["to_ms"] - parameters["from_ms"]) // 60_000
        body = b"robot_id,at\n" + b"r,1\n" * (minutes * BYTES_PER_MINUTE // 4)
        with self.lock:
            self.queries += 1
            self.produced += len(body)
        return body


@contextmanager
def served(
    app, config: uvicorn.Config | None = None
) -> Iterator[tuple[int, asyncio.AbstractEventLoop]]:
    """`app` on a real uvicorn in a thread (`config`, or uvicorn's defaults on a free
    port): its port and its event loop."""
    if config is None:
        config = uvicorn.Config(app, host="127.0.0.1", port=0, log_config=None, lifespan="off")
    server = uvicorn.Server(config)
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(server.serve(),), daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.02)
    try:
        yield server.servers[0].sockets[0].getsockname()[1], loop
    finally:
        server.should_exit = True
        thread.join(10)


def _silent_get(port: int, path: str) -> socket.socket:
    """Sends a request and reads nothing: the server's writes fill the socket buffers."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    return sock


def test_an_export_nobody_reads_is_produced_a_few_mb_ahead_then_aborted() -> None:
    """Four clients ask for a 7-day CSV and never read: each export is produced only a few
    MB ahead (the pipe, the transport and the sockets hold that much), not its ~40 MB;
    at MAPSERVICE_API_EXPORT_DEADLINE_S the server cuts them and the producers stop,
    freeing the exports' workers for the next client."""
    store = EndlessCsvStore()
    settings = Settings(
        api_export_workers=4,
        api_export_queue=0,
        api_caller_concurrency=4,
        api_export_deadline_s=3.0,
    )
    app = create_app(settings, store)
    path = f"/api/v1/exports/tables/robot-poses?from={T0}&to={T0 + 7 * 86_400_000}"
    with served(app) as (port, _):
        socks = [_silent_get(port, path) for _ in range(4)]
        time.sleep(2.0)
        produced = store.produced
        assert 0 < produced <= 4 * 16 * 1024 * 1024, (
            f"{produced / 1e6:.0f} MB produced for 4 clients that never read"
        )
        time.sleep(3.0)  # past the deadline: the exports are cut, the producers stop
        stopped = store.queries
        time.sleep(1.0)
        assert store.queries == stopped
        for sock in socks:
            sock.close()
        # The workers are free again: a client that reads gets its export.
        reply = TestClient(app).get(
            f"/api/v1/exports/tables/robot-poses?from={T0}&to={T0 + 3_600_000}"
        )
        assert reply.status_code == 200 and reply.text.startswith("robot_id,at\n")


def test_an_export_that_cannot_start_within_the_deadline_is_a_503() -> None:
    """Before its first byte an export past the deadline is answered 503 naming the setting."""
    release = threading.Event()

    class SlowMeta(MemoryStore):
        def latest_meta(self):
            release.wait(10)
            return None

    client = TestClient(create_app(Settings(api_export_deadline_s=0.5), SlowMeta()))
    reply = client.get(f"/api/v1/exports/replay.mcap?from={T0}&to={T0 + 1000}")
    release.set()
    assert reply.status_code == 503
    assert "MAPSERVICE_API_EXPORT_DEADLINE_S" in reply.json()["detail"]


def test_the_pipe_holds_at_most_its_chunks_and_stops_its_producer_when_aborted() -> None:
    """The producer's writes block once max_chunks wait unread; abort() makes them raise."""

    async def scenario():
        pipe = BoundedPipe(asyncio.get_running_loop(), chunk_bytes=1024, max_chunks=4)
        written, outcome = [0], []

        def producer():
            try:
                while True:
                    pipe.write(b"x" * 1024)
                    written[0] += 1024
            except ExportAborted:
                outcome.append("aborted")

        thread = threading.Thread(target=producer, daemon=True)
        thread.start()
        await asyncio.sleep(0.5)
        held = written[0]
        pipe.abort()
        await asyncio.get_running_loop().run_in_executor(None, thread.join, 5)
        return held, outcome

    held, outcome = asyncio.run(scenario())
    assert held <= 4 * 1024 and outcome == ["aborted"]


def test_csv_slices_carry_the_header_once_and_cover_the_window() -> None:
    """A window's CSV in slices: one header, every slice's rows, consecutive windows."""
    windows = []

    class Recording:
        database = "db"

        def export_query(self, sql, parameters, fmt):
            windows.append((parameters["from_ms"], parameters["to_ms"]))
            return b"robot_id,at\n" + f"r,{parameters['from_ms']}\n".encode()

    chunks = []

    class Out:
        def write(self, data):
            chunks.append(data)

    write_csv_slices(Recording(), "robot-poses", T0, T0 + 5 * 3_600_000, None, Out())
    body = b"".join(chunks).decode()
    assert body.count("robot_id,at") == 1
    assert windows[0][0] == T0 and windows[-1][1] == T0 + 5 * 3_600_000
    assert all(a[1] == b[0] for a, b in zip(windows, windows[1:]))
    assert body.splitlines()[1:] == [f"r,{f}" for f, _ in windows]


def _handshake(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        (
            f"GET /api/v1/live HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return sock


def test_a_live_client_that_does_not_read_is_dropped() -> None:
    """A WebSocket client that reads nothing while large messages flow: once a send has
    waited MAPSERVICE_API_LIVE_SEND_TIMEOUT_S the server closes it and the hub forgets it;
    a client that reads keeps its stream."""
    hub = LiveHub(queue_size=1000)
    app = create_app(Settings(api_live_send_timeout_s=1.0), MemoryStore(), live_hub=hub)
    with served(app) as (port, loop):
        silent = _handshake(port)
        deadline = time.monotonic() + 5
        while hub.subscribers < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert hub.subscribers == 1
        big = {"type": "pose", "robotId": "r", "blob": "x" * 100_000}
        deadline = time.monotonic() + 20
        while hub.subscribers and time.monotonic() < deadline:
            loop.call_soon_threadsafe(hub.publish, [big] * 20)
            time.sleep(0.1)
        assert hub.subscribers == 0, "the client that never read is still subscribed"
        silent.close()
