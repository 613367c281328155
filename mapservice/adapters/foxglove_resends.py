"""Which channels' current messages a Foxglove server sends again, and when. A client that
subscribes to a channel gets its current message at once (the protocol keeps no last
message), but sending it is work (the floor is a grid of the whole map, built and sent to
every client of the channel: the SDK has no per-client send), and a subscribe is a
message of a few dozen bytes a client may send thousands of times a second (subscribe,
unsubscribe, subscribe...). So a channel asked for again while its resend is pending is
not asked twice, and one sent less than `every_s` ago is sent once more when that is up:
a flood of subscribes costs one resend per channel per `every_s`, not one per message.

Thread-safe: the SDK's threads ask, the server's worker takes what is due.

May depend on: nothing of the service's."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

# A channel's current messages go out again at most this often (a later subscriber to a
# channel sent less than this long ago gets them when it is up).
RESEND_EVERY_S = 1.0


class PacedResends:
    """The channels whose current messages are to be sent again (`ask`), handed out as
    they fall due (`due`)."""

    def __init__(
        self, every_s: float = RESEND_EVERY_S, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.every_s, self.clock = every_s, clock
        self._pending: set[str] = set()
        self._last: dict[str, float] = {}  # topic -> when it was last handed out
        self._lock = threading.Lock()

    def ask(self, topic: str) -> bool:
        """A client subscribed to `topic`; whether it was not pending already (the caller
        wakes its worker then; otherwise that is done)."""
        with self._lock:
            if topic in self._pending:
                return False
            self._pending.add(topic)
            return True

    def due(self) -> list[str]:
        """The pending topics to send again now (no longer pending); the others wait until
        `every_s` after their last."""
        now = self.clock()
        with self._lock:
            out = sorted(
                t
                for t in self._pending
                if t not in self._last or now - self._last[t] >= self.every_s
            )
            for topic in out:
                self._pending.discard(topic)
                self._last[topic] = now
            return out
