"""Heatmaps of the floor over a span (up to the retention): occupancy (robot-seconds per
cell), dwell (seconds stopped), mean speed and incidents per cell, on square cells of a
multiple of 0.5 m (mapservice/core/heatmaps.py has the rule); as JSON cells, a translucent
PNG or a CSV of every measure. A sync route: the read and the picture run on the reads'
threads (and in the reads' admission pool), never on the event loop."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.responses import Response
from pydantic import BaseModel

from mapservice.core.heatmap_render import bounds, heatmap_csv, heatmap_png
from mapservice.core.heatmaps import (
    DEFAULT_CELL_M,
    FINEST_CELL_M,
    MAX_CELL_FACTOR,
    UNITS,
    CountedIncidents,
    Heatmap,
    HeatmapCell,
    Kind,
    cell_factor,
)

from ..access import READ
from ..deps import ClockDep, HeatmapsDep, IncidentsDep, SettingsDep, WindowQuery

router = APIRouter(prefix="/api/v1/heatmap", tags=["heatmaps"], dependencies=[Depends(READ)])
# Cells with a value, at most: a 0.5 m grid of 500 m x 500 m. More is a finer grid than
# anyone can read; a coarser cell answers.
MAX_CELLS = 1_000_000
MAX_INCIDENTS = 100_000
MAX_SCALE = 16
MAX_PNG_PIXELS = 16_000_000


class HeatmapBox(BaseModel):
    i0: int  # the lowest cell column and row with a value
    j0: int
    columns: int
    rows: int


class HeatmapSummary(BaseModel):
    """What a heatmap's picture needs beside it (its legend and where it lies): the PNG
    answer carries it in its SUMMARY_HEADER, so a page asks once for both."""

    kind: Kind
    unit: str
    from_ms: int
    to_ms: int
    cell_m: float  # cell (i, j) covers x in [i, i + 1) * cell_m, y in [j, j + 1) * cell_m
    max: float  # the largest value (0 without a cell)
    total: float  # the values' sum (occupancy: robot-seconds; mean speed: meaningless)
    box: HeatmapBox | None  # the cells' bounding box (None without a cell)
    incidents_truncated: bool  # more than MAX_INCIDENTS incidents: counts are of the first


class HeatmapGrid(HeatmapSummary):
    cells: list[tuple[int, int, float]]  # (i, j, value), by (i, j); cells without one left out


# The PNG answer's summary of its heatmap (HeatmapSummary as JSON, without the cells).
SUMMARY_HEADER = "X-Heatmap-Summary"


@router.get(
    "",
    operation_id="getHeatmap",
    response_model=HeatmapGrid,
    responses={
        200: {
            "content": {"image/png": {}, "text/csv": {}},
            "headers": {
                SUMMARY_HEADER: {
                    "description": "PNG only: the heatmap's HeatmapSummary as JSON (the "
                    "grid without its cells: kind, unit, span, cell size, max, total, box)",
                    "schema": {"type": "string"},
                }
            },
        }
    },
    description="A heatmap of [from, to) (windows up to the retention): occupancy "
    "(robot-seconds: each robot counts once per second it reported, in the cell of its first "
    "pose of that second), dwell (those seconds with the robot slower than the incidents' "
    "moving threshold), speed (their mean speed, m/s, each from the robot's previous second "
    "when no longer than the offline threshold before) or incidents (found, meeting the "
    f"window, counted where they were), on cells of `cell` metres (a multiple of "
    f"{FINEST_CELL_M} m up to {MAX_CELL_FACTOR * FINEST_CELL_M:g} m). format=json: the cells "
    "with a value; png: their bounding box, `scale` pixels a cell, north up, transparent "
    "where empty, coloured from the lowest to the largest value, with the grid's summary "
    f"(everything but the cells) as JSON in its {SUMMARY_HEADER} header, so that one request "
    "draws it with its legend; csv: every measure of every "
    f"cell. 400 for a bad cell size or scale; 422 for more than {MAX_CELLS:,} cells.",
)
def get_heatmap(
    window: WindowQuery,
    kind: Annotated[Kind, Query(description="occupancy, dwell, speed or incidents")],
    cell: Annotated[float, Query(description="The cells' side in metres")] = DEFAULT_CELL_M,
    format: Annotated[Literal["json", "png", "csv"], Query()] = "json",
    scale: Annotated[int, Query(description=f"PNG pixels a cell, 1 to {MAX_SCALE}")] = 1,
    *,
    heatmaps: HeatmapsDep,
    incidents: IncidentsDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> HeatmapGrid | Response:
    try:
        factor = cell_factor(cell)
    except ValueError as exc:
        raise HTTPException(400, str(exc)) from None
    if not 1 <= scale <= MAX_SCALE:
        raise HTTPException(400, f"scale ({scale}) must be between 1 and {MAX_SCALE}")
    f, t = window.in_retention(settings.retention_ms, settings, clock.now_ms())
    # Each read only where it is shown: the incidents kind is counted from the incidents
    # alone, the other kinds from the samples alone; the CSV has every measure.
    cells: list[HeatmapCell] = []
    if format == "csv" or kind != "incidents":
        cells = heatmaps.heatmap_cells(f, t, factor, limit=MAX_CELLS + 1)
    if len(cells) > MAX_CELLS:
        raise HTTPException(
            422,
            f"more than {MAX_CELLS:,} cells of {cell:g} m hold a value; use a larger cell "
            f"(e.g. cell={min(MAX_CELL_FACTOR, factor * 2) * FINEST_CELL_M:g}) or a shorter span",
        )
    counted = CountedIncidents({}, False)
    if format == "csv" or kind == "incidents":
        counted = incidents.incidents_per_cell(f, t, factor, limit=MAX_INCIDENTS)
    heatmap = Heatmap(f, t, factor * FINEST_CELL_M, cells, counted.cells)
    if format == "csv":
        return Response(
            heatmap_csv(heatmap),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="heatmap-{f}-{t}.csv"'},
        )
    values = heatmap.values(kind)
    box = bounds(values)
    summary = HeatmapSummary(
        kind=kind,
        unit=UNITS[kind],
        from_ms=f,
        to_ms=t,
        cell_m=heatmap.cell_m,
        max=max(values.values(), default=0.0),
        total=sum(values.values()),
        box=HeatmapBox(i0=box[0], j0=box[1], columns=box[2], rows=box[3]) if box else None,
        incidents_truncated=counted.truncated,
    )
    if format == "png":
        pixels = (box[2] * box[3] if box else 1) * scale * scale
        if pixels > MAX_PNG_PIXELS:
            raise HTTPException(
                422,
                f"the picture would be {pixels:,} pixels, more than {MAX_PNG_PIXELS:,}; "
                "use a smaller scale or a larger cell",
            )
        return Response(
            heatmap_png(values, scale),
            media_type="image/png",
            headers={SUMMARY_HEADER: summary.model_dump_json()},
        )
    return HeatmapGrid(
        **summary.model_dump(), cells=[(i, j, v) for (i, j), v in sorted(values.items())]
    )
