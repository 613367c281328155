"""What a client may send on /api/v1/live, against the API's own uvicorn configuration
(`api_server_config`): the stream takes no message, so one over
`WEBSOCKET_MAX_MESSAGE_BYTES` (text or binary, compressed or not: with
`MAPSERVICE_API_LIVE_COMPRESSION` a few kB on the wire inflate to the size uvicorn
allows, 16 MiB a message by default) is refused with 1009 before the server inflates or
holds more than that, and the probes answer at once meanwhile."""

from __future__ import annotations

import contextlib
import threading
import time
import zlib
from collections.abc import Iterator

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from mapservice.api.app import create_app
from mapservice.api.composition import api_server_config
from mapservice.api.limits import WEBSOCKET_MAX_MESSAGE_BYTES
from mapservice.api.live_hub import LiveHub
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.api.test_foxglove_frames import frame
from tests.api.test_slow_clients import served

MESSAGE_TOO_BIG = 1009


@contextlib.contextmanager
def api_served(compression: bool) -> Iterator[tuple[int, LiveHub]]:
    """The API on uvicorn as `mapservice api` configures it, in a thread."""
    settings = Settings(api_host="127.0.0.1", api_port=0, api_live_compression=compression)
    hub = LiveHub()
    app = create_app(settings, MemoryStore(), live_hub=hub)
    config = api_server_config(app, settings)
    config.lifespan = "off"
    config.timeout_graceful_shutdown = 1  # a live route runs until its client goes
    with served(app, config) as (port, _):
        yield port, hub


def _close_code(ws, message: str | bytes) -> int | None:
    """Sends `message`; the close code the server answers with within 1.5 s, None if it
    keeps the connection open."""
    with contextlib.suppress(ConnectionClosed):
        ws.send(message)
    try:
        ws.recv(timeout=1.5)
    except TimeoutError:
        return None
    except ConnectionClosed:
        pass
    return ws.protocol.close_rcvd.code if ws.protocol.close_rcvd else -1


@pytest.mark.parametrize("compression", [False, True], ids=["plain", "deflate"])
@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
@pytest.mark.parametrize("extra", [-1, 0, 1, 4 * 1024 * 1024])
def test_a_client_message_over_the_limit_is_refused_with_1009(compression, binary, extra):
    """Just inside the limit the connection stays (the stream ignores it); one byte over
    it is closed with 1009, megabytes over too (as soon as the frame's length is read). Compressed, zeros (what a bomb is made of)
    cross the wire in a few kB."""
    size = WEBSOCKET_MAX_MESSAGE_BYTES + extra
    message: str | bytes = bytes(size) if binary else "\0" * size
    with (
        api_served(compression) as (port, _),
        connect(
            f"ws://127.0.0.1:{port}/api/v1/live",
            compression="deflate" if compression else None,
            max_size=None,
            close_timeout=0.5,  # the server reads no more once it holds a message
        ) as ws,
    ):
        assert bool(ws.protocol.extensions) == compression
        code = _close_code(ws, message)
    if extra <= 0:
        assert code is None
    elif extra == 1:
        assert code == MESSAGE_TOO_BIG
    else:  # closed while the client still writes: its close frame may be lost to a reset
        assert code in (MESSAGE_TOO_BIG, -1)


# The probes are timed: run alone, as the other heavy requests' (tests/api/test_heavy_requests.py).
@pytest.mark.integration
@pytest.mark.alone
def test_compressed_bombs_on_many_connections_leave_the_probes_fast():
    """With compression on, 10 connections each send a 16 MiB message of zeros (16 kB on
    the wire): each is closed with 1009 once the limit is inflated, and /healthz answers
    within half a second throughout (each used to be inflated whole and held)."""
    bomb = zlib.compressobj(9, zlib.DEFLATED, -12)
    wire = bomb.compress(bytes(16 * 1024 * 1024)) + bomb.flush(zlib.Z_SYNC_FLUSH)
    assert len(wire) < 32 * 1024
    with api_served(True) as (port, _):
        slowest = 0.0
        stop = threading.Event()

        def probe() -> None:
            nonlocal slowest
            with httpx.Client(base_url=f"http://127.0.0.1:{port}") as client:
                while not stop.is_set():
                    started = time.monotonic()
                    assert client.get("/healthz").status_code == 200
                    slowest = max(slowest, time.monotonic() - started)
                    time.sleep(0.02)

        prober = threading.Thread(target=probe)
        prober.start()
        codes = []
        try:
            for _ in range(10):
                with connect(
                    f"ws://127.0.0.1:{port}/api/v1/live",
                    compression="deflate",
                    max_size=None,
                    close_timeout=0.5,
                ) as ws:
                    # The deflated frame as the extension would send it (RSV1 set).
                    ws.socket.sendall(_deflated_binary_frame(wire[:-4]))
                    try:
                        ws.recv(timeout=1.5)
                    except (TimeoutError, ConnectionClosed):
                        pass
                    codes.append(ws.protocol.close_rcvd.code if ws.protocol.close_rcvd else None)
        finally:
            stop.set()
            prober.join()
    assert codes == [MESSAGE_TOO_BIG] * 10, codes
    assert slowest < 0.5, slowest


def _deflated_binary_frame(payload: bytes) -> bytes:
    """A client's masked binary frame, FIN and RSV1 (permessage-deflate) set."""
    plain = frame(0x2, payload)
    return bytes([plain[0] | 0x40]) + plain[1:]


@pytest.mark.parametrize(
    "sent",
    [[], ["ping"], [b"\x00\x01"], ["x" * WEBSOCKET_MAX_MESSAGE_BYTES] * 3, ["hello"] * 50],
    ids=["nothing", "a text", "a binary", "three at the limit", "fifty"],
)
def test_a_client_that_closes_frees_its_slot_at_once_whatever_it_sent(sent):
    """The stream takes no message, yet reads and drops what a client sends: a message left
    unread stopped the server reading the connection, so the client's close went unseen and
    its slot (one of MAPSERVICE_API_MAX_LIVE_CLIENTS) stayed taken on a quiet floor until
    the keepalive gave up. The floor is quiet here: no event is sent to notice it by."""
    with api_served(False) as (port, hub):
        with connect(f"ws://127.0.0.1:{port}/api/v1/live", close_timeout=2) as ws:
            deadline = time.monotonic() + 5
            while hub.subscribers < 1 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert hub.subscribers == 1
            for message in sent:
                ws.send(message)
        deadline = time.monotonic() + 5
        while hub.subscribers and time.monotonic() < deadline:
            time.sleep(0.02)
        assert hub.subscribers == 0, "the closed client still holds its slot"
