"""The clock the live views judge silences by: the wall clock less how far the stored
batches are behind the stream.

A robot is silent when nothing of it was heard for robot_offline_after_s. Judged by the
wall clock alone, a processors replica that is behind (catching up after a restart or a
rebalance, or slower than the fleet for a while) would find every robot silent: every
robot offline in the fleet panel, an `offline` incident and an alert for each, then all of
them ended when their poses arrive, and at a few thousand robots that burst of work keeps
it behind. What a batch says about how far behind it is: its newest event's receive time
(the gateway's clock, when the event entered the pipeline) against the wall clock when it
is stored; a poll that finds nothing to read says it is not behind at all. A silence is
judged against the stream as far as it is stored, so a robot is offline when the stream
shows it silent, however late the stream is read; when the stream is caught up this is the
wall clock less the pipeline's own delay (a few hundred ms), and when nothing comes (a
quiet floor, a plant cut off) the wall clock.

Never earlier than it said before (a growing lag holds it still rather than turning it
back), and never later than the wall clock.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from prometheus_client import Gauge

from mapservice.core.events import Envelope

BEHIND = Gauge(
    "mapservice_processors_behind_seconds",
    "How far the newest stored batch was behind the stream when it was stored "
    "(its newest event's receive time against the processors' clock)",
)


class StreamClock:
    def __init__(self, wall_ms: Callable[[], int]) -> None:
        self.wall_ms = wall_ms
        self.behind_ms = 0
        self._said = -(2**62)

    def stored(self, events: Sequence[Envelope]) -> None:
        """A batch is in the history: how far behind the stream it was."""
        if not events:
            return
        newest = max(e.receive_time_ms for e in events)
        self.behind_ms = max(0, self.wall_ms() - newest)
        BEHIND.set(self.behind_ms / 1000)

    def caught_up(self) -> None:
        """A poll found nothing waiting: whatever silence there is, the stream holds it."""
        self.behind_ms = 0
        BEHIND.set(0)

    def now_ms(self) -> int:
        self._said = max(self._said, self.wall_ms() - self.behind_ms)
        return self._said
