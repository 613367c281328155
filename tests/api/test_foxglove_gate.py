"""The Foxglove server's gate on real sockets: every upgrade request is admitted or refused
by the API's rules (read access and tokens, Host, Origin, the client cap, the path), an
admitted one reaches its upstream byte for byte, and a client that does not read is
dropped instead of holding the server's data. The upstream here is a plain socket server
that answers the upgrade and then sends without end."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import socket
import time

import pytest

from mapservice.api.credentials import Credentials
from mapservice.api.foxglove_gate import FoxgloveGate, Upstream
from mapservice.settings import Settings

READER, WRITER, METRICS = "r" * 40, "w" * 40, "m" * 40
SWITCHING = (
    b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
)


class Upstream101:
    """Answers any request with 101 and then, if `flood`, sends 64 kB blocks until closed:
    as fast as they are taken, or `rate` bytes a second."""

    def __init__(self, flood: bool, rate: float | None = None) -> None:
        self.flood, self.rate = flood, rate
        self.heads: list[bytes] = []
        self.port = 0
        self.closed = 0

    async def start(self) -> None:
        server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = server.sockets[0].getsockname()[1]

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            self.heads.append(await reader.readuntil(b"\r\n\r\n"))
            writer.write(SWITCHING)
            block = b"x" * 65536
            while self.flood:
                writer.write(block)
                await writer.drain()
                if self.rate is not None:
                    await asyncio.sleep(len(block) / self.rate)
            await reader.read()  # until the gate closes its side
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self.closed += 1
            writer.close()


def settings(**overrides) -> Settings:
    base = {
        "api_reader_tokens": READER,
        "api_writer_tokens": WRITER,
        "api_metrics_token": METRICS,
        "foxglove_max_clients": 3,
        "foxglove_send_timeout_s": 0.5,
    }
    return Settings(**{**base, **overrides})


def request(path="/", host="127.0.0.1:8765", headers=(), protocol="foxglove.sdk.v1") -> bytes:
    lines = [
        f"GET {path} HTTP/1.1",
        f"Host: {host}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
        "Sec-WebSocket-Version: 13",
        f"Sec-WebSocket-Protocol: {protocol}",
        *headers,
    ]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


async def exchange(port: int, raw: bytes) -> tuple[int, bytes]:
    """Sends one request; the status of the answer and the answer's first bytes."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(raw)
    await writer.drain()
    async with asyncio.timeout(5):
        head = await reader.readuntil(b"\r\n\r\n")
        body = await reader.read(400) if not head.startswith(b"HTTP/1.1 101") else b""
    writer.close()
    return int(head.split(b" ")[1]), head + body


async def gate_over(upstream: Upstream101, s: Settings) -> tuple[FoxgloveGate, int]:
    await upstream.start()

    async def route() -> Upstream:
        return Upstream(upstream.port)

    gate = FoxgloveGate(s, Credentials(s), {"/": route, "/replay": route})
    return gate, await gate.start("127.0.0.1", 0)


# Every way a token can come, with every kind of token, under both read-access modes.
TOKENS = {"none": None, "reader": READER, "writer": WRITER, "metrics": METRICS, "wrong": "x" * 40}
CARRIERS = {
    "header": lambda t: ({"headers": (f"Authorization: Bearer {t}",)}, "/"),
    "query": lambda t: ({}, f"/?token={t}"),
    "subprotocol": lambda t: ({"protocol": f"foxglove.sdk.v1, bearer.{t}"}, "/"),
}


def expected_status(access: str, token: str) -> int:
    if access == "open":
        return 101  # open means open, a stale token too (as the API's reads)
    return {"none": 401, "wrong": 401, "metrics": 403}.get(token, 101)


@pytest.mark.parametrize("access", ["open", "token"])
def test_tokens_are_the_apis_read_access(access):
    async def main() -> list[str]:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(upstream, settings(api_read_access=access))
        wrong = []
        for (token_name, token), (carrier, make) in itertools.product(
            TOKENS.items(), CARRIERS.items()
        ):
            if token is None and carrier != "header":
                continue
            kwargs, path = make(token) if token else ({}, "/")
            status, answer = await exchange(port, request(path, **kwargs))
            want = expected_status(access, token_name)
            if status != want:
                wrong.append(
                    f"{token_name} by {carrier}: {status}, expected {want}: {answer[-200:]!r}"
                )
            elif status == 401:
                assert b"WWW-Authenticate" in answer and b"token" in answer
        await gate.stop()
        return wrong

    assert asyncio.run(main()) == []


@pytest.mark.parametrize(
    ("host", "origin", "status"),
    [
        ("127.0.0.1:8765", None, 101),
        ("localhost:8765", "http://localhost:8765", 101),  # a page of the server's own host
        ("10.1.2.3:8765", None, 101),  # an address is no name an attacker can point here
        ("evil.example:8765", None, 421),  # DNS rebinding: a name not ours
        ("127.0.0.1:8765", "https://evil.example", 403),  # another site's page
        ("127.0.0.1:8765", "http://127.0.0.1:9999", 403),  # another port is another origin
        ("127.0.0.1:8765", "https://dash.example", 101),  # MAPSERVICE_API_ALLOWED_ORIGINS
    ],
)
def test_host_and_origin_as_the_api_checks_them(host, origin, status):
    async def main() -> int:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(
            upstream, settings(api_allowed_origins=["https://dash.example"])
        )
        headers = (f"Origin: {origin}",) if origin else ()
        got, _ = await exchange(port, request(host=host, headers=headers))
        await gate.stop()
        return got

    assert asyncio.run(main()) == status


def test_unknown_paths_and_non_upgrades_are_answered_not_piped():
    async def main() -> tuple[int, int, int]:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(upstream, settings())
        unknown, _ = await exchange(port, request("/nope"))
        plain, _ = await exchange(port, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        replay, _ = await exchange(port, request("/replay"))
        await gate.stop()
        return unknown, plain, replay

    assert asyncio.run(main()) == (404, 400, 101)


def test_client_cap_refuses_one_more_and_frees_a_place_when_one_leaves():
    async def main() -> None:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(upstream, settings(foxglove_max_clients=3))
        held = []
        for _ in range(3):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(request())
            assert (await reader.readuntil(b"\r\n\r\n")).startswith(b"HTTP/1.1 101")
            held.append(writer)
        status, answer = await exchange(port, request())
        assert status == 503 and b"MAPSERVICE_FOXGLOVE_MAX_CLIENTS" in answer
        held.pop().close()
        deadline = time.monotonic() + 5
        while gate.clients >= 3 and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        assert (await exchange(port, request()))[0] == 101
        for w in held:
            w.close()
        await gate.stop()

    asyncio.run(main())


def test_a_client_that_does_not_read_is_dropped_and_one_that_reads_is_not():
    async def main() -> None:
        upstream = Upstream101(flood=True)
        gate, port = await gate_over(upstream, settings(foxglove_send_timeout_s=0.5))
        # A reader: takes 20 MB in time, far more than any buffer between it and the upstream.
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(request())
        await reader.readuntil(b"\r\n\r\n")
        got = 0
        async with asyncio.timeout(20):
            while got < 20 * 2**20:
                got += len(await reader.read(2**20))
        writer.close()
        # A client that never reads: its socket's buffers fill, then the gate drops it.
        sleeper = socket.create_connection(("127.0.0.1", port))
        sleeper.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sleeper.sendall(request())
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not (gate.clients == 0 and upstream.closed >= 2):
            await asyncio.sleep(0.1)
        assert gate.clients == 0, "the client that does not read was not dropped"
        assert upstream.closed >= 2  # and the upstream's side of it closed too
        sleeper.close()
        await gate.stop()

    asyncio.run(main())


@pytest.mark.parametrize("reads_per_s", [24.0, 36.0, 48.0])
def test_a_client_reading_slower_than_it_is_sent_is_dropped_and_one_keeping_up_is_not(
    reads_per_s,
):
    """The upstream sends 4 MB/s (a busy floor's grids). A client reading less (64 kB reads,
    `reads_per_s` of them: 1.5-3 MB/s) takes bytes all along, so no timeout ends it, yet it
    falls further behind for ever: the gate used to wait for it and leave the backlog to the
    SDK's queue, counted in messages of up to megabytes each. It is dropped once it is
    foxglove_client_buffer_mb behind; a client reading as fast as it is sent stays."""
    rate = 4 * 2**20

    async def main() -> None:
        upstream = Upstream101(flood=True, rate=rate)
        gate, port = await gate_over(
            upstream, settings(foxglove_send_timeout_s=1.0, foxglove_client_buffer_mb=1.0)
        )
        keeper_r, keeper_w = await asyncio.open_connection("127.0.0.1", port)
        keeper_w.write(request())
        await keeper_r.readuntil(b"\r\n\r\n")
        # Its receive buffer small from the start, so that what it has not read shows soon.
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 65536)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
        slow_r, slow_w = await asyncio.open_connection(sock=sock, limit=65536)
        slow_w.write(request())
        await slow_r.readuntil(b"\r\n\r\n")

        async def keep_up() -> int:
            got = 0
            while data := await keeper_r.read(2**20):
                got += len(data)
            return got

        keeper = asyncio.ensure_future(keep_up())
        started = time.monotonic()
        dropped_after = None
        assert gate.clients == 2
        while time.monotonic() - started < 20:
            # (What its socket holds it may read on after the gate dropped it.)
            with contextlib.suppress(ConnectionError):
                await slow_r.read(65536)
            if gate.clients < 2:
                dropped_after = time.monotonic() - started
                break
            await asyncio.sleep(1 / reads_per_s)
        assert dropped_after is not None, "the client reading a trickle was never dropped"
        # Once its socket's buffers (a few MB at most) and the gate's MB filled.
        assert dropped_after < 15, dropped_after
        assert not keeper.done(), "the client keeping up was dropped"
        assert gate.clients == 1
        keeper_w.close()
        await asyncio.wait_for(keeper, 10)
        await gate.stop()

    asyncio.run(main())


def test_the_request_reaches_the_upstream_unchanged():
    async def main() -> None:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(upstream, settings())
        raw = request("/?token=" + READER, headers=("X-Probe: 1",))
        assert (await exchange(port, raw))[0] == 101
        await gate.stop()
        assert upstream.heads == [raw]

    asyncio.run(main())


@pytest.mark.parametrize(
    ("offered", "upstream_gets", "client_gets"),
    [
        ("foxglove.websocket.v1", "foxglove.sdk.v1", "foxglove.websocket.v1"),
        ("foxglove.sdk.v1", "foxglove.sdk.v1", "foxglove.sdk.v1"),
        (
            "foxglove.websocket.v1, foxglove.sdk.v1",
            "foxglove.websocket.v1, foxglove.sdk.v1",
            "foxglove.sdk.v1",
        ),
    ],
)
def test_a_client_offering_the_protocols_older_name_is_served(offered, upstream_gets, client_gets):
    """Lichtblick and the npm client offer only `foxglove.websocket.v1`, which the SDK no
    longer accepts: the gate names it `foxglove.sdk.v1` to the SDK and back to the client."""

    async def main() -> tuple[bytes, bytes]:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(upstream, settings())
        status, answer = await exchange(port, request(protocol=offered))
        await gate.stop()
        assert status == 101
        return upstream.heads[0], answer

    head, answer = asyncio.run(main())
    assert f"Sec-WebSocket-Protocol: {upstream_gets}\r\n".encode() in head
    assert f"Sec-WebSocket-Protocol: {client_gets}\r\n".encode() in answer
