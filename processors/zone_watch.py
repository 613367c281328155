"""Zone violations: a robot's stored pose inside a keep-out zone, found after each stored
batch (like conflicts) by the pixel rule of the keep-out mask, so a violation is exactly a
pose on a pixel nav2 would treat as keep-out.

The keep-out zones are held as a label raster of the map (which zone covers each pixel),
rebuilt from the store whenever a zone edit is stored: checking a pose is one lookup. A
pose is checked against the zones standing when the batch is stored; a pose older than
the zone it lies in (a late one) is not a violation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from mapservice.adapters.costmap_filters import grid_of
from mapservice.core.annotations import Zone, ZoneViolation
from mapservice.core.events import Envelope, pose_of
from mapservice.core.ports import AnnotationReader, TimeTravelReader
from mapservice.core.zone_masks import Grid, keep_out_labels, pixel_of


class ZoneSource(AnnotationReader, TimeTravelReader, Protocol):
    """The standing zones and the map meta they are rasterised on."""


class KeepOutWatch:
    def __init__(self) -> None:
        self.grid: Grid | None = None
        self.labels = np.zeros((0, 0), dtype=np.int32)
        self.ids: list[str] = []
        self.since: dict[str, int] = {}  # zone id -> when it began (its current life)

    def rebuild(self, store: ZoneSource, at_ms: int) -> None:
        """The keep-out zones standing at `at_ms`, rasterised on the map (blocking: run in
        the store's thread)."""
        self.grid = grid_of(store.latest_meta())
        zones: list[tuple[str, Zone]] = []
        self.since = {}
        for c in store.annotations_at(at_ms):
            if isinstance(c.annotation, Zone) and c.annotation.kind == "keep_out":
                zones.append((c.annotation_id, c.annotation))
                self.since[c.annotation_id] = c.created_ms
        if self.grid is None or not zones:
            self.labels, self.ids = np.zeros((0, 0), dtype=np.int32), []
            return
        self.labels, self.ids = keep_out_labels(self.grid, zones)

    def violations(self, events: Sequence[Envelope]) -> list[ZoneViolation]:
        if self.grid is None or not self.ids:
            return []
        out = []
        for e in events:
            pose = pose_of(e.payload)
            if pose is None:
                continue
            x, y = pose.position[0], pose.position[1]
            pixel = pixel_of(self.grid, x, y)
            if pixel is None or not (label := int(self.labels[pixel])):
                continue
            zone_id = self.ids[label - 1]
            if e.event_time_ms >= self.since.get(zone_id, 0):
                out.append(ZoneViolation(e.event_time_ms, e.robot_id, zone_id, x, y))
        return out
