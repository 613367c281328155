"""The Foxglove server's public port. The SDK's WebSocket server checks no credential, Host
or Origin and takes any number of clients, so it listens on a loopback port of its own and
this gate stands in front: it reads each connection's HTTP upgrade request, answers it
itself when the API's rules refuse it (the reader token where reads are closed: 401/403; a
Host that is not one of the service's names: 421; an Origin of another site: 403; the
client cap: 503), and otherwise hands the request and then the connection's bytes, both
ways, to the SDK server its path names (`/`: live; `/replay`: a replay session's own).

The gate reads the SDK's side of a connection as it comes and holds what the client has
not taken yet, up to `foxglove_client_buffer_mb`: a client further behind (it reads slower
than its subscriptions send) is dropped, as is one that takes no bytes for
`foxglove_send_timeout_s` while some wait for it. Waiting for the client instead would move
the backlog into the SDK's own queue for it, which is counted in messages (`foxglove_backlog`),
not bytes: a thousand floor grids of megabytes each for a client reading a trickle. A subscription the SDK lost to its own
race (a channel advertised before the SDK recorded it) is sent again
(foxglove_resubscribe.py)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

import structlog
from fastapi import HTTPException

from mapservice.settings import Settings

from .credentials import (
    Credentials,
    Scope,
    bearer_token,
    decide,
    subprotocol_token,
)
from .foxglove_frames import SubscriptionCount, close_frame
from .foxglove_resubscribe import Resubscribe, ServerStream
from .limits import allowed_hosts, host_allowed, origin_allowed

log = structlog.get_logger(__name__)

MAX_HEAD_BYTES = 16 * 1024
HEAD_TIMEOUT_S = 10.0
_CHUNK = 64 * 1024


@dataclass(frozen=True)
class Upstream:
    """Where an admitted connection goes: the SDK server's loopback port, and what to do
    when the connection ends (a replay session stops its server)."""

    port: int
    release: Callable[[], Awaitable[None]] | None = None


# A path's upstream, made for each admitted connection ("/": the live server's).
Route = Callable[[], Awaitable[Upstream]]


class Refused(Exception):
    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status, self.reason = status, reason


_STATUS_TEXT = {
    400: "Bad Request",
    401: "Unauthorized",
    403: "Forbidden",
    404: "Not Found",
    421: "Misdirected Request",
    503: "Service Unavailable",
}


# The SDK's server speaks the protocol under its current name only; clients that offer just
# the name it had before (Lichtblick, the npm @foxglove/ws-protocol client) speak the same
# messages: the gate names it for them, both ways.
SDK_SUBPROTOCOL = "foxglove.sdk.v1"
OLD_SUBPROTOCOL = "foxglove.websocket.v1"


def offered_subprotocols(headers: dict[str, str]) -> list[str]:
    return [p.strip() for p in headers.get("sec-websocket-protocol", "").split(",") if p.strip()]


def _set_header(head: bytes, name: str, value: str) -> bytes:
    """`head` with header `name` (any case) replaced by `value`."""
    lines = head.split(b"\r\n")
    key = name.lower().encode()
    out = [
        f"{name}: {value}".encode() if line.split(b":", 1)[0].strip().lower() == key else line
        for line in lines
    ]
    return b"\r\n".join(out)


@dataclass(frozen=True)
class Request:
    path: str
    query: dict[str, list[str]]
    headers: dict[str, str]  # lower-case names; a repeated header keeps its last value


def parse_head(head: bytes) -> Request:
    """The request line and headers of an HTTP/1.1 upgrade request (Refused 400 if not)."""
    try:
        lines = head.decode("latin-1").split("\r\n")
        method, target, version = lines[0].split(" ")
    except ValueError:
        raise Refused(400, "not an HTTP request line") from None
    if method != "GET" or not version.startswith("HTTP/1."):
        raise Refused(400, "a Foxglove client opens a WebSocket: GET with Upgrade: websocket")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        if not line:
            continue
        name, sep, value = line.partition(":")
        if not sep:
            raise Refused(400, "malformed header line")
        headers[name.strip().lower()] = value.strip()
    if headers.get("upgrade", "").lower() != "websocket":
        raise Refused(400, "a Foxglove client opens a WebSocket: GET with Upgrade: websocket")
    split = urlsplit(target)
    return Request(split.path or "/", parse_qs(split.query), headers)


class FoxgloveGate:
    """Admits or refuses each connection of the public port, then pipes it to its upstream."""

    def __init__(
        self, settings: Settings, credentials: Credentials, routes: dict[str, Route]
    ) -> None:
        self.settings, self.credentials, self.routes = settings, credentials, routes
        self.hosts = allowed_hosts(settings)
        self.clients = 0
        self.refused = 0
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self, host: str, port: int) -> int:
        """Listens; returns the port (`port` 0: a free one)."""
        self._server = await asyncio.start_server(
            self._connection, host, port, limit=MAX_HEAD_BYTES
        )
        return int(self._server.sockets[0].getsockname()[1])

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(BaseException):
                await task

    def admit(self, request: Request, address: str) -> Route:
        """The request's route if the API's rules let it in, else Refused."""
        if not host_allowed(request.headers.get("host"), self.hosts):
            raise Refused(
                421,
                "this host name is not one of the service's (MAPSERVICE_API_ALLOWED_HOSTS)",
            )
        if not origin_allowed(
            request.headers.get("origin"),
            request.headers.get("host"),
            self.settings.api_allowed_origins,
        ):
            raise Refused(
                403, "this origin may not open the Foxglove stream (MAPSERVICE_API_ALLOWED_ORIGINS)"
            )
        token = (
            bearer_token(request.headers.get("authorization"))
            or subprotocol_token(request.headers.get("sec-websocket-protocol", ""))
            or next(reversed(request.query.get("token", [])), None)
        )
        try:
            decide(self.credentials, Scope.READ, token, address, "the Foxglove stream")
        except HTTPException as exc:
            raise Refused(exc.status_code, str(exc.detail)) from None
        route = self.routes.get(request.path.rstrip("/") or "/")
        if route is None:
            raise Refused(404, f"no Foxglove stream at {request.path[:80]!r}: / (live) or /replay")
        if self.clients >= self.settings.foxglove_max_clients:
            raise Refused(
                503,
                f"too many Foxglove clients ({self.settings.foxglove_max_clients}, "
                "MAPSERVICE_FOXGLOVE_MAX_CLIENTS); try again later",
            )
        return route

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        peer = writer.get_extra_info("peername")
        address = str(peer[0]) if peer else "unknown"
        admitted = False
        try:
            try:
                async with asyncio.timeout(HEAD_TIMEOUT_S):
                    head = await reader.readuntil(b"\r\n\r\n")
                route = self.admit(parse_head(head), address)
            except Refused as refused:
                await self._refuse(writer, refused)
                return
            except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                return  # no request head in time, or one too large: nothing to answer
            self.clients += 1
            admitted = True
            try:
                upstream = await route()
            except Exception as exc:  # a replay session that could not start
                log.warning("foxglove upstream failed to start", error=str(exc))
                await self._refuse(writer, Refused(503, f"the stream could not start: {exc}"))
                return
            offered = offered_subprotocols(parse_head(head).headers)
            renamed = SDK_SUBPROTOCOL not in offered and OLD_SUBPROTOCOL in offered
            if renamed:
                head = _set_header(head, "Sec-WebSocket-Protocol", SDK_SUBPROTOCOL)
            try:
                await self._pipe(head, reader, writer, upstream.port, renamed)
            finally:
                if upstream.release is not None:
                    await upstream.release()
        except (ConnectionError, OSError):
            pass
        finally:
            if admitted:
                self.clients -= 1
            writer.close()
            try:
                async with asyncio.timeout(5.0):
                    await writer.wait_closed()
            except Exception:  # unsent bytes it does not take: thrown away
                writer.transport.abort()
            if task is not None:
                self._tasks.discard(task)

    async def _refuse(self, writer: asyncio.StreamWriter, refused: Refused) -> None:
        self.refused += 1
        body = (refused.reason + "\n").encode()
        head = (
            f"HTTP/1.1 {refused.status} {_STATUS_TEXT.get(refused.status, 'Error')}\r\n"
            "Content-Type: text/plain; charset=utf-8\r\n"
            f"Content-Length: {len(body)}\r\n"
            + ('WWW-Authenticate: Bearer realm="mapservice"\r\n' if refused.status == 401 else "")
            + "Connection: close\r\n\r\n"
        )
        log.info("foxglove client refused", status=refused.status, reason=refused.reason)
        with contextlib.suppress(Exception):
            writer.write(head.encode() + body)
            async with asyncio.timeout(2.0):
                await writer.drain()

    async def _pipe(
        self,
        head: bytes,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        port: int,
        renamed: bool = False,
    ) -> None:
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", port, limit=_CHUNK)
        timeout_s = self.settings.foxglove_send_timeout_s
        most_behind = int(self.settings.foxglove_client_buffer_mb * 2**20)
        # No pause below the budget: what the client has not taken is counted, not waited on.
        writer.transport.set_write_buffer_limits(high=most_behind + _CHUNK)
        up_writer.write(head)
        try:
            async with asyncio.timeout(HEAD_TIMEOUT_S):
                answer = await up_reader.readuntil(b"\r\n\r\n")
        except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            log.warning("foxglove upstream gave no answer to the upgrade", port=port)
            up_writer.close()
            return
        upgraded = answer.startswith(b"HTTP/1.1 101")
        if renamed and upgraded:  # the answer names the protocol as the client offered it
            answer = _set_header(answer, "Sec-WebSocket-Protocol", OLD_SUBPROTOCOL)
        writer.write(answer)

        counted = SubscriptionCount(self.settings.foxglove_max_subscriptions)
        # The SDK's frames are read once it switched protocols (not an HTTP error's body).
        server_side = ServerStream(counted) if upgraded else None
        # The gate's own frames for the SDK wait for the end of the client's message.
        own_frames: list[bytes] = []
        timers: list[asyncio.TimerHandle] = []
        loop = asyncio.get_running_loop()

        def to_server(frame: bytes) -> None:
            own_frames.append(frame)
            if counted.at_boundary:
                up_writer.write(b"".join(own_frames))
                own_frames.clear()

        def again(resubscribe: Resubscribe) -> None:
            log.debug("foxglove subscription sent again", channel=resubscribe.channel_id)
            timers.append(loop.call_later(resubscribe.delay_s, to_server, resubscribe.frame()))

        behind = _Behind(writer.transport, most_behind, timeout_s, loop.time)

        async def copy(
            src: asyncio.StreamReader, dst: asyncio.StreamWriter, to_client: bool
        ) -> None:
            while data := await src.read(_CHUNK):
                if not to_client and (reason := counted.feed(data)):
                    log.info("foxglove client closed", reason=reason)
                    writer.write(close_frame(1008, reason))
                    with contextlib.suppress(Exception):
                        async with asyncio.timeout(2.0):
                            await writer.drain()
                    return
                if to_client and server_side is not None:
                    data, lost = server_side.feed(data)
                    for resubscribe in lost:
                        again(resubscribe)
                dst.write(data)
                if not to_client and own_frames and counted.at_boundary:
                    dst.write(b"".join(own_frames))
                    own_frames.clear()
                if to_client:
                    if reason := behind.wrote(len(data)):
                        log.info("foxglove client dropped", reason=reason)
                        # Closed at once, its unsent bytes thrown away: a close would wait
                        # for them to be sent first, i.e. for ever.
                        dst.transport.abort()
                        return
                else:
                    await dst.drain()

        tasks = [
            asyncio.ensure_future(copy(reader, up_writer, False)),
            asyncio.ensure_future(copy(up_reader, writer, True)),
        ]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for timer in timers:
                timer.cancel()
            for t in tasks:
                t.cancel()
            for t in tasks:
                with contextlib.suppress(BaseException):
                    await t
            up_writer.close()
            with contextlib.suppress(Exception):
                await up_writer.wait_closed()


class _Behind:
    """How far a client is behind what the gate wrote it: the bytes its connection has not
    taken yet, and when it last took any."""

    def __init__(
        self,
        transport: asyncio.WriteTransport,
        most_bytes: int,
        timeout_s: float,
        clock: Callable[[], float],
    ) -> None:
        self.transport, self.most_bytes, self.timeout_s, self.clock = (
            transport,
            most_bytes,
            timeout_s,
            clock,
        )
        self.written = self.taken = 0
        self.took_at = clock()

    def wrote(self, n: int) -> str | None:
        """After `n` more bytes were written: why the client must go, or None."""
        self.written += n
        pending = self.transport.get_write_buffer_size()
        now = self.clock()
        if self.written - pending > self.taken or not pending:
            self.taken, self.took_at = self.written - pending, now
        if pending > self.most_bytes:
            return (
                f"{pending} bytes behind, more than MAPSERVICE_FOXGLOVE_CLIENT_BUFFER_MB: "
                "it reads slower than its subscriptions send"
            )
        if now - self.took_at > self.timeout_s:
            return (
                f"it took no bytes for {self.timeout_s:g} s "
                "(MAPSERVICE_FOXGLOVE_SEND_TIMEOUT_S): it does not read"
            )
        return None
