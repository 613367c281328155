"""ROS occupancy-grid maps (PGM + YAML) and their cut into chunks."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from .events import MapMetaSet

UNKNOWN = 205


@dataclass(frozen=True)
class RosMap:
    pixels: np.ndarray  # uint8, shape (height, width), row 0 at the top as in the PGM
    resolution: float
    origin: tuple[float, float, float]
    comment: str = ""

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])


def load_ros_map(yaml_path: str | Path) -> RosMap:
    """Loads a map_server YAML and its image (paths relative to the YAML file)."""
    yaml_path = Path(yaml_path)
    doc = yaml.safe_load(yaml_path.read_text())
    image_path = (yaml_path.parent / doc["image"]).resolve()
    with Image.open(image_path) as img:
        pixels = np.asarray(img.convert("L"), dtype=np.uint8)
    origin = tuple(float(v) for v in doc.get("origin", (0.0, 0.0, 0.0)))
    return RosMap(pixels, float(doc["resolution"]), origin)  # type: ignore[arg-type]


def meta_for(ros_map: RosMap, chunk_width: int = 100, chunk_height: int = 100) -> MapMetaSet:
    rows = -(-ros_map.height // chunk_height)
    cols = -(-ros_map.width // chunk_width)
    return MapMetaSet(
        width=ros_map.width, height=ros_map.height, chunk_width=chunk_width,
        chunk_height=chunk_height, chunk_rows=rows, chunk_cols=cols, comment=ros_map.comment,
        resolution=ros_map.resolution, origin=ros_map.origin,
    )


def slice_chunks(ros_map: RosMap, chunk_width: int = 100,
                 chunk_height: int = 100) -> dict[tuple[int, int], bytes]:
    """(row, column) -> chunk pixels; the map is padded with 'unknown' to whole chunks."""
    meta = meta_for(ros_map, chunk_width, chunk_height)
    padded = np.full((meta.chunk_rows * chunk_height, meta.chunk_cols * chunk_width), UNKNOWN,
                     dtype=np.uint8)
    padded[: ros_map.height, : ros_map.width] = ros_map.pixels
    return {
        (r, c): padded[r * chunk_height:(r + 1) * chunk_height,
                       c * chunk_width:(c + 1) * chunk_width].tobytes()
        for r in range(meta.chunk_rows) for c in range(meta.chunk_cols)
    }


def free_cells_metres(ros_map: RosMap, stride: int = 10) -> np.ndarray:
    """World coordinates (x, y) in metres of free pixels, sampled every `stride` pixels."""
    ys, xs = np.nonzero(ros_map.pixels[::stride, ::stride] >= 250)
    px, py = xs * stride, ys * stride
    ox, oy, _ = ros_map.origin
    # Image row 0 is the top; the map origin is the lower-left pixel.
    wx = ox + (px + 0.5) * ros_map.resolution
    wy = oy + (ros_map.height - py - 0.5) * ros_map.resolution
    return np.stack([wx, wy], axis=1)
