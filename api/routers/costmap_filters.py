"""The zones at any instant as nav2 costmap filters: the mask as map_server files (PGM and
YAML, aligned with the map's origin and resolution) and the costmap_filter_info_server
parameters that read it. A robot on nav2 points a map_server at mask.yaml (kept beside
mask.pgm) and a costmap_filter_info_server at filter-info.yaml.

- keepout: type 0, trinary PGM (0 = keep out, 254 = free), base 0, multiplier 1.
- speed: type 1 (`unit=percent`: mask value = % of the maximum speed) or 2 (`unit=m/s`:
  limit = multiplier x mask value), a raw PGM (pixel = mask value, 0 = no limit); only the
  zones whose limit is in that unit, the lowest limit where zones overlap.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Path, Query
from fastapi.responses import Response

from mapservice.adapters.costmap_filters import (
    filter_info_yaml,
    grid_of,
    keep_out_pgm,
    mask_yaml,
    speed_pgm,
)
from mapservice.core.annotations import Zone
from mapservice.core.ports import AnnotationReader, TimeTravelReader
from mapservice.core.zone_masks import (
    KEEP_OUT,
    FilterInfo,
    Grid,
    keep_out_mask,
    speed_filter_info,
    speed_mask,
)

from ..access import READ
from ..annotation_state import RecentEdits, standing
from ..deps import AnnotationsDep, AtDep, HistoryDep, RecentEditsDep

router = APIRouter(
    prefix="/api/v1/costmap-filters", tags=["annotations"], dependencies=[Depends(READ)]
)


FilterPath = Annotated[Literal["keepout", "speed"], Path(description="keepout or speed")]
UnitQuery = Annotated[
    Literal["percent", "m/s"],
    Query(
        description=(
            "speed only: the unit of the limits in the mask (zones in the other unit are left out)"
        )
    ),
]
PGM = "image/x-portable-graymap"
YAML = "application/yaml"
_PGM_RESPONSE: dict[int | str, dict[str, Any]] = {
    200: {"content": {PGM: {}}, "description": "The mask image (binary PGM)"}
}
_YAML_RESPONSE: dict[int | str, dict[str, Any]] = {
    200: {"content": {YAML: {}}, "description": "map_server / filter info YAML"}
}


def _zones(
    recent: RecentEdits, history: TimeTravelReader, annotations: AnnotationReader, at: int
) -> tuple[Grid, list[Zone]]:
    grid = grid_of(history.latest_meta())
    if grid is None:
        raise HTTPException(
            409,
            "the map has no resolution and origin yet, so a mask cannot be "
            "aligned with it; upload the map (`mapservice map upload`) first",
        )
    zones = [
        c.annotation
        for c in standing(recent, annotations, at).values()
        if isinstance(c.annotation, Zone)
    ]
    return grid, zones


def _info(filter_: str, zones: list[Zone], unit: str) -> FilterInfo:
    return (
        FilterInfo(KEEP_OUT, 0.0, 1.0) if filter_ == "keepout" else speed_filter_info(zones, unit)
    )


@router.get(
    "/{filter_}/mask.pgm",
    operation_id="getCostmapFilterMask",
    response_class=Response,
    responses=_PGM_RESPONSE,
)
def get_mask(
    filter_: FilterPath,
    recent: RecentEditsDep,
    history: HistoryDep,
    annotations: AnnotationsDep,
    at: AtDep,
    unit: UnitQuery = "percent",
) -> Response:
    """The mask at `at` (default now): one pixel per map pixel, row 0 at the top."""
    grid, zones = _zones(recent, history, annotations, at)
    if filter_ == "keepout":
        body = keep_out_pgm(keep_out_mask(grid, zones))
    else:
        body = speed_pgm(speed_mask(grid, zones, unit)[0])
    return Response(
        body,
        media_type=PGM,
        headers={
            "Content-Disposition": f'attachment; filename="{filter_}.pgm"',
            "X-Mask-At-Ms": str(at),
        },
    )


@router.get(
    "/{filter_}/mask.yaml",
    operation_id="getCostmapFilterMaskYaml",
    response_class=Response,
    responses=_YAML_RESPONSE,
)
def get_mask_yaml(
    filter_: FilterPath,
    recent: RecentEditsDep,
    history: HistoryDep,
    annotations: AnnotationsDep,
    at: AtDep,
) -> Response:
    """The map_server YAML of the mask: the map's resolution and origin; `image: mask.pgm`
    (save both files side by side)."""
    grid, _ = _zones(recent, history, annotations, at)
    return Response(
        mask_yaml(grid, "mask.pgm", "trinary" if filter_ == "keepout" else "raw"), media_type=YAML
    )


@router.get(
    "/{filter_}/filter-info.yaml",
    operation_id="getCostmapFilterInfo",
    response_class=Response,
    responses=_YAML_RESPONSE,
)
def get_filter_info(
    filter_: FilterPath,
    recent: RecentEditsDep,
    history: HistoryDep,
    annotations: AnnotationsDep,
    at: AtDep,
    unit: UnitQuery = "percent",
) -> Response:
    """The costmap_filter_info_server parameters for the mask: type (0 keep-out, 1 speed %,
    2 speed m/s), base and multiplier (filter value = base + multiplier x mask value)."""
    _, zones = _zones(recent, history, annotations, at)
    info = _info(filter_, zones, unit)
    node = "keepout_filter_info_server" if filter_ == "keepout" else "speed_filter_info_server"
    return Response(filter_info_yaml(info, node, f"/{filter_}_filter_mask"), media_type=YAML)
