"""The incidents' ports: where the stored findings are read from and announced to."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from mapservice.core.incident_model import Incident


class IncidentReader(Protocol):
    """The incidents found in the history (ClickHouse: `incident_reads`)."""

    def incidents(
        self,
        from_ms: int,
        to_ms: int,
        kinds: Sequence[str] = (),
        robot_id: str | None = None,
        limit: int = 10_000,
    ) -> list[Incident]:
        """The incidents meeting [from_ms, to_ms) (start < to_ms, end >= from_ms), of
        `kinds` (all if empty) and involving `robot_id` (any if None), by start, kind and
        id; as last found, retracted ones left out."""


class IncidentFeed(Protocol):
    """Where stored incident findings go for live viewers (mapservice/core/live_incidents.py);
    never blocks."""

    def publish_incidents(
        self, found: Sequence[Incident], retracted: Sequence[Incident], found_ms: int
    ) -> None:
        """Called after the findings are stored, so listed."""
