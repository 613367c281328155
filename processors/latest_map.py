"""The latest map as the live views hold it: per chunk, its winning write over all stored
event times; each change is advertised to the robots (advertising.py)."""

from __future__ import annotations

from collections.abc import Sequence

from prometheus_client import Counter

from mapservice.core.events import ChunkUpdated, Envelope
from mapservice.core.liveview import apply_chunks
from mapservice.core.ports import ChunkState, TimeTravelReader

from .advertising import AdvertisementQueue

VIEW_CHANGES = Counter("mapservice_latest_map_changes_total", "Changes of the live latest map")


class LatestMap:
    def __init__(self, ads: AdvertisementQueue | None) -> None:
        self.ads = ads
        self.latest: dict[tuple[int, int], ChunkState] = {}

    def load(self, history: TimeTravelReader, horizon_ms: int) -> None:
        """The map at `horizon_ms` (blocking: run in the store's thread)."""
        self.latest = {(c.row, c.column): c for c in history.map_at(horizon_ms)}

    @staticmethod
    def touched_by(events: Sequence[Envelope]) -> bool:
        return any(isinstance(e.payload, ChunkUpdated) for e in events)

    def apply(self, events: Sequence[Envelope]) -> None:
        """The batch's chunk writes that win, each advertised."""
        for e in apply_chunks(self.latest, events):
            VIEW_CHANGES.inc()
            if self.ads is not None:
                self.ads.chunk_changed(e)
