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

import numpy as np
from prometheus_client import Counter

from mapservice.adapters.costmap_filters import grid_of
from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationRemoved,
    Zone,
    ZoneViolation,
    zone_advertisement,
)
from mapservice.core.events import Envelope, pose_of
from mapservice.core.ports import AnnotationReader, TimeTravelReader
from mapservice.core.zone_masks import Grid, keep_out_labels, pixel_of

from .advertising import AdvertisementQueue

ZONE_VIOLATIONS = Counter(
    "mapservice_zone_violations_total", "Stored poses found inside a keep-out zone"
)


class KeepOutWatch:
    def __init__(self) -> None:
        self.grid: Grid | None = None
        self.labels = np.zeros((0, 0), dtype=np.int32)
        self.ids: list[str] = []
        self.since: dict[str, int] = {}  # zone id -> when it began (its current life)

    def rebuild(self, history: TimeTravelReader, annotations: AnnotationReader, at_ms: int) -> None:
        """The keep-out zones standing at `at_ms` (`annotations`), rasterised on the map
        whose meta `history` holds (blocking: run in the store's thread)."""
        self.grid = grid_of(history.latest_meta())
        zones: list[tuple[str, Zone]] = []
        self.since = {}
        for c in annotations.annotations_at(at_ms):
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


class Zones:
    """The zones standing now: an edit that creates, changes or removes one is advertised
    on `topic` (robots then fetch the masks); edits of points of interest are not the
    robots' business. Holds the keep-out raster stored poses are checked against."""

    def __init__(
        self,
        history: TimeTravelReader,
        annotations: AnnotationReader,
        ads: AdvertisementQueue | None,
        topic: str,
        public_base_url: str,
    ) -> None:
        self.history, self.annotations = history, annotations
        self.ads, self.topic, self.public_base_url = ads, topic, public_base_url
        self.ids: set[str] = set()
        self.keep_out = KeepOutWatch()  # touched only in the store thread

    def load(self, horizon_ms: int) -> None:
        """The zones standing at `horizon_ms` (blocking: run in the store's thread)."""
        self.ids = {
            c.annotation_id
            for c in self.annotations.annotations_at(horizon_ms)
            if isinstance(c.annotation, Zone)
        }
        self.rebuild_keep_out(horizon_ms)

    def rebuild_keep_out(self, horizon_ms: int) -> None:
        self.keep_out.rebuild(self.history, self.annotations, horizon_ms)

    def edited(self, e: Envelope) -> bool:
        """Whether an annotation edit touches a zone (advertised if so)."""
        p = e.payload
        if not isinstance(p, AnnotationCreated | AnnotationChanged | AnnotationRemoved):
            return False
        was_zone = p.annotation_id in self.ids
        is_zone = not isinstance(p, AnnotationRemoved) and isinstance(p.annotation, Zone)
        if is_zone:
            self.ids.add(p.annotation_id)
        else:
            self.ids.discard(p.annotation_id)
        if (was_zone or is_zone) and self.ads is not None:
            ad = zone_advertisement(
                p.annotation_id,
                e.type.removeprefix("annotation."),
                e.event_time_ms,
                p.author,
                self.public_base_url,
            )
            self.ads.to_topic(self.topic, ad)
        return was_zone or is_zone

    def violations(self, events: Sequence[Envelope]) -> list[ZoneViolation]:
        """Stored poses inside a standing keep-out zone."""
        if not self.keep_out.ids:
            return []
        return self.keep_out.violations(events)
