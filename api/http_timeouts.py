"""A deadline for a request's line and headers, which uvicorn does not have.

uvicorn's `timeout_keep_alive` closes a connection that stays silent between requests,
but every byte received cancels it, and nothing bounds how long a request's head may take:
a client that sends `GET / HTTP/1.1\\r\\n` and then one header byte every few seconds holds
a connection (and its buffers) for ever; a few hundred such sockets (slowloris) take the
API's connections. ASGI middleware cannot help: the app is called only once the head is
complete. So the deadline lives in uvicorn's h11 protocol: armed when a connection opens
and after every response, disarmed once h11 has parsed a whole request head; on expiry
the connection is closed. Bodies have their own deadline (api/limits.py BodyLimit).
"""

from __future__ import annotations

import asyncio

import h11
from prometheus_client import Counter
from uvicorn.protocols.http.h11_impl import H11Protocol

HEADER_TIMEOUTS = Counter(
    "mapservice_api_header_timeouts_total",
    "Connections closed because a request's head did not arrive in "
    "time (MAPSERVICE_API_HEADER_TIMEOUT_S)",
)


class HeaderDeadlineProtocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline for each request head."""

    header_timeout_s: float = 10.0
    _deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        # IDLE until h11 has the whole head; after it (a body, a response, an upgrade to a
        # WebSocket, which has pings of its own) this deadline is no longer ours to keep.
        if self.conn.their_state is not h11.IDLE:
            self._disarm()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm()  # the next request's head, from now (a pipelined one is parsed already)

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(self.header_timeout_s, self._expired)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expired(self) -> None:
        self._deadline = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            HEADER_TIMEOUTS.inc()
            self.transport.close()


def header_deadline_protocol(timeout_s: float) -> type[HeaderDeadlineProtocol]:
    """The protocol class for uvicorn.Config(http=...) with this deadline."""
    return type(
        "HeaderDeadlineProtocol", (HeaderDeadlineProtocol,), {"header_timeout_s": timeout_s}
    )
