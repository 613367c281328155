"""A heatmap as a picture (PNG, translucent, to lay over the floor) and as a table (CSV).

The picture covers the cells' bounding box, `scale` pixels a cell, north up (its first row
is the highest cell row j, as the map's PNG has the highest y first); a cell's colour is
its value over the largest value on the ramp below (the replay UI's legend draws the same
ramp), empty cells are transparent.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping

import numpy as np

from mapservice.core.heatmaps import Heatmap
from mapservice.core.render import png

# Low to high: dark blue, blue, green, yellow, red (the UI's legend: replay-ui/src/lib/heatmap.ts).
RAMP = np.array(
    [(49, 54, 149), (69, 117, 180), (116, 196, 118), (254, 224, 75), (215, 48, 39)],
    dtype=np.float64,
)
ALPHA = 180  # translucent: the floor shows through
CSV_COLUMNS = (
    "i",
    "j",
    "x_m",
    "y_m",
    "cell_m",
    "occupancy_s",
    "dwell_s",
    "mean_speed_m_s",
    "incidents",
)


def bounds(values: Mapping[tuple[int, int], float]) -> tuple[int, int, int, int] | None:
    """(i0, j0, columns, rows) of the cells' bounding box; None without a cell."""
    if not values:
        return None
    i0, i1 = min(i for i, _ in values), max(i for i, _ in values)
    j0, j1 = min(j for _, j in values), max(j for _, j in values)
    return i0, j0, i1 - i0 + 1, j1 - j0 + 1


def ramp(fraction: np.ndarray) -> np.ndarray:
    """RGB (uint8, ... x 3) of fractions in [0, 1] on the ramp, linearly between stops."""
    at = np.clip(fraction, 0.0, 1.0) * (len(RAMP) - 1)
    low = np.minimum(np.floor(at).astype(int), len(RAMP) - 2)
    mix = (at - low)[..., None]
    # Halves rounded up, as the legend's Math.round: the same colour on the page and in the PNG.
    rgb: np.ndarray = np.floor(RAMP[low] * (1 - mix) + RAMP[low + 1] * mix + 0.5).astype(np.uint8)
    return rgb


def heatmap_png(values: Mapping[tuple[int, int], float], scale: int = 1) -> bytes:
    """The cells' picture (module docstring); one transparent pixel without a cell."""
    box = bounds(values)
    if box is None:
        return png(np.zeros((1, 1, 4), dtype=np.uint8))
    i0, j0, columns, rows = box
    top = j0 + rows - 1
    image = np.zeros((rows, columns, 4), dtype=np.uint8)
    keys = list(values)
    ii = np.fromiter((i - i0 for i, _ in keys), dtype=np.int64, count=len(keys))
    jj = np.fromiter((top - j for _, j in keys), dtype=np.int64, count=len(keys))
    v = np.fromiter(values.values(), dtype=np.float64, count=len(keys))
    highest = v.max()
    image[jj, ii, :3] = ramp(v / highest if highest > 0 else np.zeros_like(v))
    image[jj, ii, 3] = ALPHA
    if scale > 1:
        image = image.repeat(scale, axis=0).repeat(scale, axis=1)
    return png(image)


def heatmap_csv(heatmap: Heatmap) -> str:
    """Every cell with a sample or an incident, by (i, j): where it is (its corner of
    lowest x and y, metres) and every measure."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    size = heatmap.cell_m
    for i, j, samples, still, speed, incidents in heatmap.rows():
        writer.writerow(
            [
                i,
                j,
                f"{i * size:g}",
                f"{j * size:g}",
                f"{size:g}",
                samples,
                still,
                "" if speed is None else f"{speed:.6g}",
                incidents,
            ]
        )
    return out.getvalue()
