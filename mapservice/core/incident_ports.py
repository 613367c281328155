"""Where the stored incident findings are announced to (the live stream)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from mapservice.core.incident_model import Incident


class IncidentFeed(Protocol):
    """Where stored incident findings go for live viewers (mapservice/core/live_incidents.py);
    never blocks."""

    def publish_incidents(
        self, found: Sequence[Incident], retracted: Sequence[Incident], found_ms: int
    ) -> None:
        """Called after the findings are stored, so listed."""
