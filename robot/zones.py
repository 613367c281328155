"""Operators' zones as a simulated robot uses them: the keep-out zones as pixels it must
not plan through, the speed zones as a limit per pixel.

The pixels are the keep-out mask's (`mapservice.core.zone_masks`: a pixel is in a zone
when its centre is): a robot that never stands on one never stands where nav2's keep-out
filter, or the processors' zone watch, would see it inside a zone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapservice.core.annotations import AnnotationError, Zone, from_doc
from mapservice.core.zone_masks import Grid, rasterise_window

from .planning import PlanGrid, grid_for


@dataclass(frozen=True, eq=False)
class FloorZones:
    """The zones standing, rasterised on the map (image rows x columns, row 0 at the top)."""

    keep_out: np.ndarray | None = None  # bool: inside a keep-out zone; None: no keep-out zone
    speed_m_s: np.ndarray | None = None  # float32 limit in m/s, inf where none; None: no speed zone
    zones: tuple[tuple[str, Zone], ...] = ()  # (id, zone), as the service listed them


NO_ZONES = FloorZones()


def speed_limit_m_s(zone: Zone, full_speed_m_s: float) -> float:
    """A speed zone's limit in m/s: a percentage is of the robot's own top speed (as nav2's
    speed filter reads a percent mask), m/s is the limit itself."""
    assert zone.speed_limit is not None
    if zone.speed_unit == "percent":
        return full_speed_m_s * zone.speed_limit / 100.0
    return zone.speed_limit


def floor_zones(zones: Sequence[tuple[str, Zone]], grid: Grid, full_speed_m_s: float) -> FloorZones:
    """The keep-out pixels and the speed limit per pixel (overlapping speed zones: the
    lowest limit wins); note zones change nothing."""
    keep_out: np.ndarray | None = None
    speed: np.ndarray | None = None
    for _id, zone in zones:
        if zone.kind not in ("keep_out", "speed_limit"):
            continue
        r0, c0, inside = rasterise_window(grid, (zone.polygon, *zone.holes))
        rows, cols = slice(r0, r0 + inside.shape[0]), slice(c0, c0 + inside.shape[1])
        if zone.kind == "keep_out":
            if keep_out is None:
                keep_out = np.zeros((grid.height, grid.width), dtype=bool)
            keep_out[rows, cols] |= inside
        elif zone.speed_limit is not None:
            if speed is None:
                speed = np.full((grid.height, grid.width), np.inf, dtype=np.float32)
            region = speed[rows, cols]
            region[inside] = np.minimum(region[inside], speed_limit_m_s(zone, full_speed_m_s))
    return FloorZones(keep_out, speed, tuple(zones))


def blocked_grid(
    free: np.ndarray, keep_out: np.ndarray, resolution: float, cell_m: float, robot_radius_m: float
) -> PlanGrid:
    """The planning grid with the keep-out pixels as not drivable: a cell holding one is
    blocked, and the inflation by the robot's radius keeps the robot's body off the zone
    as it keeps it off a rack."""
    return grid_for(free & ~keep_out, resolution, cell_m, robot_radius_m)


def zones_from_listing(doc: Any) -> list[tuple[str, Zone]]:
    """The zones in the API's listAnnotations answer ({"annotations": [{"id", "annotation"}]}),
    by id; points of interest are left out. Raises ValueError on an answer of another shape."""
    if not isinstance(doc, dict) or not isinstance(doc.get("annotations"), list):
        raise ValueError(
            "the annotations listing has no 'annotations' list; is the URL the "
            "service's API (GET /api/v1/annotations)?"
        )
    out: list[tuple[str, Zone]] = []
    for item in doc["annotations"]:
        body = item.get("annotation") if isinstance(item, dict) else None
        if not isinstance(body, dict) or body.get("shape") != "zone":
            continue
        try:  # stored zones were validated when made: read them as they are
            zone = from_doc(body, check=False)
            annotation_id = str(item["id"])
        except (AnnotationError, KeyError) as exc:
            raise ValueError(
                f"the annotations listing holds a zone that cannot be read: {exc}"
            ) from None
        if isinstance(zone, Zone):
            out.append((annotation_id, zone))
    return sorted(out, key=lambda z: z[0])
