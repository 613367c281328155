"""nav2 costmap filter masks as map_server files: a PGM and its YAML, aligned with the
map, plus the costmap_filter_info_server parameters; and a mask file read back.

Keep-out masks are `trinary` (pixel 0 = occupied = keep out, 254 = free), as nav2's own
keep-out masks are. Speed masks are `raw`: map_server takes the pixel value itself as the
OccupancyGrid value (0 = no limit, 1..100 read through base + multiplier x value).
"""

from __future__ import annotations

import io

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError

from mapservice.adapters.ros_map import OCCUPIED, RosMap, classify, read_pgm_header
from mapservice.core.events import MapMetaSet
from mapservice.core.zone_masks import MASK_KEEP_OUT, FilterInfo, Grid

FREE_PIXEL, OCCUPIED_PIXEL = 254, 0  # what map_saver writes for free and occupied
# The formats a mask may come in (map_server reads PGM and PNG); Pillow's other decoders,
# and their flaws, are never reached from a request.
MASK_FORMATS = ("PNG", "PPM")
MAX_MASK_PIXELS = 64_000_000  # 8,000 x 8,000: a mask decodes to one byte a pixel, and more


class MaskFileError(ValueError):
    """A mask file that cannot be read or does not fit the map; the message says why."""


def grid_of(meta: MapMetaSet | None) -> Grid | None:
    """The map's raster, or None while the map has no geometry (resolution and origin)."""
    if meta is None or meta.resolution is None or meta.origin is None:
        return None
    return Grid(
        meta.width,
        meta.height,
        float(meta.resolution),
        float(meta.origin[0]),
        float(meta.origin[1]),
    )


def pgm_bytes(pixels: np.ndarray) -> bytes:
    pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
    height, width = pixels.shape
    return (
        f"P5\n# mapservice costmap filter mask\n{width} {height}\n255\n".encode() + pixels.tobytes()
    )


def keep_out_pgm(mask: np.ndarray) -> bytes:
    """OccupancyGrid values (100 keep out, 0 free) as a trinary PGM's pixels."""
    return pgm_bytes(np.where(mask == MASK_KEEP_OUT, OCCUPIED_PIXEL, FREE_PIXEL).astype(np.uint8))


def speed_pgm(mask: np.ndarray) -> bytes:
    """OccupancyGrid values 0..100 as a raw PGM (pixel = value)."""
    return pgm_bytes(mask)


def mask_yaml(grid: Grid, image: str, mode: str) -> str:
    """The map_server YAML of a mask: the map's resolution and origin, so nav2 lays the
    mask exactly over the map."""
    doc = {
        "image": image,
        "mode": mode,
        "resolution": grid.resolution,
        "origin": [grid.origin_x, grid.origin_y, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    return yaml.safe_dump(doc, sort_keys=False)


def filter_info_yaml(info: FilterInfo, node: str, mask_topic: str) -> str:
    """Parameters of nav2's costmap_filter_info_server node for this mask."""
    doc = {
        node: {
            "ros__parameters": {
                "use_sim_time": False,
                "type": info.type,
                "filter_info_topic": f"/{node}/filter_info",
                "mask_topic": mask_topic,
                "base": info.base,
                "multiplier": info.multiplier,
            }
        }
    }
    return yaml.safe_dump(doc, sort_keys=False)


def _decoded(image: bytes, size: tuple[int, int]) -> np.ndarray:
    """The image's grey pixels, decoded only once its header says it is `size` (width,
    height): Pillow's open reads the header alone, so a small file that would inflate to
    a huge image is refused before a pixel is decompressed."""
    if size[0] * size[1] > MAX_MASK_PIXELS:
        raise MaskFileError(
            f"the map is {size[0]} x {size[1]} px; masks of at most {MAX_MASK_PIXELS} pixels "
            "(MAX_MASK_PIXELS) are imported: draw the zones instead"
        )
    try:
        with Image.open(io.BytesIO(image), formats=MASK_FORMATS) as img:
            if img.size != size:
                raise MaskFileError(
                    f"the mask is {img.size[0]} x {img.size[1]} px but the map is "
                    f"{size[0]} x {size[1]} px; a mask covers the map exactly"
                )
            return np.asarray(img.convert("L"), dtype=np.uint8)
    except MaskFileError:
        raise
    except Image.DecompressionBombError:
        # Pillow's own guard, at open, for headers past twice Image.MAX_IMAGE_PIXELS: far
        # more pixels than any map of this service (MAX_MASK_PIXELS) has.
        raise MaskFileError(
            f"the mask image's header gives far more pixels than the map's {size[0]} x "
            f"{size[1]} px; a mask covers the map exactly"
        ) from None
    except UnidentifiedImageError:
        raise MaskFileError(
            "the mask image is not a PNG or PGM (the formats nav2's map_server reads)"
        ) from None
    except Exception as exc:  # noqa: BLE001 - Pillow raises many kinds for bad bytes
        raise MaskFileError(f"the mask image does not decode: {str(exc)[:200]}") from None


def read_mask(yaml_text: str, image: bytes, size: tuple[int, int]) -> RosMap:
    """A mask given as its YAML text and image bytes (PGM or PNG) that must be `size`
    (width, height) pixels: the map's, checked from the image's header before decoding."""
    try:
        doc = yaml.safe_load(yaml_text)
    except yaml.YAMLError as exc:
        raise MaskFileError(f"the mask YAML does not parse: {str(exc)[:200]}") from None
    if not isinstance(doc, dict) or "resolution" not in doc:
        raise MaskFileError(
            "the mask YAML needs at least 'resolution' and 'origin' (map_server format)"
        )
    try:
        resolution = float(doc["resolution"])
        origin = tuple(float(v) for v in doc.get("origin", (0.0, 0.0, 0.0)))
        negate = int(doc.get("negate", 0))
        occupied = float(doc.get("occupied_thresh", 0.65))
        free = float(doc.get("free_thresh", 0.196))
    except (TypeError, ValueError) as exc:
        raise MaskFileError(f"the mask YAML has a field of the wrong type: {exc}") from None
    if len(origin) != 3 or not resolution > 0:
        raise MaskFileError("the mask YAML needs a positive resolution and an origin [x, y, yaw]")
    maxval = 255
    if image[:2] in (b"P2", b"P5"):
        try:
            maxval = read_pgm_header(image[:4096]).maxval
        except ValueError as exc:
            raise MaskFileError(f"the mask image is not a readable PGM: {exc}") from None
    pixels = _decoded(image, size)
    if maxval != 255:
        pixels = np.rint(pixels.astype(np.float64) * maxval / 255).astype(np.uint8)
    return RosMap(
        pixels,
        resolution,
        origin,
        negate=negate,  # type: ignore[arg-type]
        occupied_thresh=occupied,
        free_thresh=free,
        mode=str(doc.get("mode", "trinary")),
        max_brightness=maxval,
    )


def keep_out_pixels(mask: RosMap, grid: Grid) -> np.ndarray:
    """The pixels a keep-out mask marks (occupied as map_server reads it), checked to lie
    exactly over the map."""
    if (mask.width, mask.height) != (grid.width, grid.height):
        raise MaskFileError(
            f"the mask is {mask.width} x {mask.height} px but the map is "
            f"{grid.width} x {grid.height} px; a mask covers the map exactly"
        )
    if (
        abs(mask.resolution - grid.resolution) > 1e-9
        or abs(mask.origin[0] - grid.origin_x) > 1e-6
        or abs(mask.origin[1] - grid.origin_y) > 1e-6
    ):
        raise MaskFileError(
            f"the mask's resolution {mask.resolution} and origin {list(mask.origin[:2])} differ "
            f"from the map's ({grid.resolution}, [{grid.origin_x}, {grid.origin_y}]); a mask "
            "must be aligned with the map"
        )
    return classify(mask) == OCCUPIED
