"""The retention's rule: which events it bounds and when one is older than it.

One rule for every place that judges an event's age: the gateway refuses a message whose
timestamp is older than the retention, and the history sink stores no such event (one
read again from Kafka after its day was dropped would otherwise bring that day back, and
the snapshots, views and conflicts built over it, until the next retention step).
"""

from __future__ import annotations

from mapservice.core.commands import CommandAcknowledged, CommandFinished, CommandIssued
from mapservice.core.events import (
    ChunkUpdated,
    Envelope,
    PoseReported,
    VdaConnectionReported,
    VdaStateReported,
)

DAY_MS = 86_400_000
DEFAULT_RETENTION_MS = 7 * DAY_MS

# The history the retention forgets by day. Not among them: the map meta, a vehicle's
# factsheet and the annotations, which are state the retention keeps however old.
RETAINED_BY_TIME = (
    ChunkUpdated,
    PoseReported,
    VdaStateReported,
    VdaConnectionReported,
    CommandIssued,
    CommandAcknowledged,
    CommandFinished,
)


def older_than_retention(ts_ms: int, now_ms: int, retention_ms: int) -> bool:
    """Whether an instant lies before the retention at `now_ms` (the service's clock): the
    boundary itself is kept."""
    return ts_ms < now_ms - retention_ms


def expired(event: Envelope, now_ms: int, retention_ms: int) -> bool:
    """Whether the retention at `now_ms` has already forgotten `event`'s time: an event of
    the history (RETAINED_BY_TIME) whose own time is older than the retention."""
    return isinstance(event.payload, RETAINED_BY_TIME) and older_than_retention(
        event.event_time_ms, now_ms, retention_ms
    )
