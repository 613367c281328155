"""Slice a map into 2019 chunks, stitch it back, meta.json, and pixel <-> metre conversion.

Chunks are keyed (row, column) with row 0 at the top of the image, as the 2019 slicer cut
them. Maps that do not divide into whole chunks are padded with the map's 'unknown' value
and cropped back on stitching, so slice-then-stitch gives back the same image.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import yaml

from mapservice.adapters.ros_map import (
    UNKNOWN,
    RosMap,
    load_ros_map,
    meta_for,
    read_pgm,
    slice_chunks,
    write_pgm,
)
from mapservice.core.events import MapMetaSet

META_FILE = "meta.json"
ROS_FILE = "map.yaml"  # PGM flavour and ROS settings of the sliced map, for stitch to write back


# --- meta.json -------------------------------------------------------------------------


def meta_to_json(meta: MapMetaSet) -> dict:
    """The 2019 meta.json (listing 8) plus `resolution` and `origin` when known."""
    return meta.to_2019()


def meta_from_json(doc: dict) -> MapMetaSet:
    """Reads a 2019 meta.json (with or without resolution/origin)."""
    origin = doc.get("origin")
    return MapMetaSet(
        width=int(doc["width"]),
        height=int(doc["height"]),
        chunk_width=int(doc["CHUNK_WIDTH"]),
        chunk_height=int(doc["CHUNK_HEIGHT"]),
        chunk_rows=int(doc["CHUNK_ROWS"]),
        chunk_cols=int(doc["CHUNK_COLS"]),
        comment=str(doc.get("comment", "")),
        max_brightness=str(doc.get("max_brightness", "255")),
        resolution=float(doc["resolution"]) if doc.get("resolution") is not None else None,
        origin=tuple(float(v) for v in origin) if origin is not None else None,  # type: ignore[arg-type]
    )


# --- pixels <-> metres (pure) ------------------------------------------------------------


def metres_geometry(meta: MapMetaSet) -> tuple[float, float, float]:
    """(resolution, origin x, origin y) of the map: what converts pixels to metres."""
    if meta.resolution is None or meta.origin is None:
        raise ValueError("the map meta has no resolution/origin; slice it from its ROS YAML")
    return meta.resolution, meta.origin[0], meta.origin[1]


def pixel_to_metres(col: float, row: float, meta: MapMetaSet) -> tuple[float, float]:
    """World (x, y) of the centre of image pixel (col, row); row 0 is the top row and the
    ROS origin is the lower-left corner of the image."""
    res, ox, oy = metres_geometry(meta)
    return ox + (col + 0.5) * res, oy + (meta.height - row - 0.5) * res


def metres_to_pixel(x: float, y: float, meta: MapMetaSet) -> tuple[int, int]:
    """Image pixel (col, row) that holds world point (x, y); may lie outside the image."""
    res, ox, oy = metres_geometry(meta)
    col = math.floor((x - ox) / res + 1e-9)
    row = meta.height - 1 - math.floor((y - oy) / res + 1e-9)
    return col, row


def chunk_of_pixel(col: int, row: int, meta: MapMetaSet) -> tuple[int, int]:
    """(chunk row, chunk column) holding image pixel (col, row)."""
    return row // meta.chunk_height, col // meta.chunk_width


def chunk_pixels(
    pixels: np.ndarray, meta: MapMetaSet, row: int, column: int, fill: int = UNKNOWN
) -> bytes:
    """One chunk of an image (padded with `fill` beyond its edges), as chunk bytes."""
    ch, cw = meta.chunk_height, meta.chunk_width
    out = np.full((ch, cw), fill, dtype=np.uint8)
    part = pixels[row * ch : (row + 1) * ch, column * cw : (column + 1) * cw]
    out[: part.shape[0], : part.shape[1]] = part
    return out.tobytes()


def paste_chunk(pixels: np.ndarray, meta: MapMetaSet, row: int, column: int, data: bytes) -> None:
    """Writes chunk bytes into an image in place, dropping the padding beyond its edges."""
    ch, cw = meta.chunk_height, meta.chunk_width
    tile = np.frombuffer(data, dtype=np.uint8).reshape(ch, cw)
    target = pixels[row * ch : (row + 1) * ch, column * cw : (column + 1) * cw]
    target[...] = tile[: target.shape[0], : target.shape[1]]


def stitch(
    chunks: dict[tuple[int, int], bytes], meta: MapMetaSet, fill: int = UNKNOWN
) -> np.ndarray:
    """The image from its chunks, cropped to the meta's width x height; a missing chunk is
    'unknown'."""
    pixels = np.full((meta.height, meta.width), fill, dtype=np.uint8)
    for (row, column), data in chunks.items():
        if 0 <= row < meta.chunk_rows and 0 <= column < meta.chunk_cols:
            paste_chunk(pixels, meta, row, column, data)
    return pixels


# --- on disk -----------------------------------------------------------------------------


def chunk_file(row: int, column: int) -> str:
    return f"chunk_{row}_{column}.pgm"


def load_map_file(path: str | Path) -> RosMap:
    """A ROS YAML, or a bare PGM (then without resolution/origin)."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        return load_ros_map(path)
    pixels, header = read_pgm(path)
    return RosMap(
        pixels,
        float("nan"),
        (float("nan"),) * 3,  # type: ignore[arg-type]
        comment="\n".join(header.comments),
        magic=header.magic,
        max_brightness=header.maxval,
    )


def _meta(ros_map: RosMap, chunk_width: int, chunk_height: int) -> MapMetaSet:
    meta = meta_for(ros_map, chunk_width, chunk_height)
    if math.isnan(ros_map.resolution):
        from msgspec.structs import replace

        meta = replace(meta, resolution=None, origin=None)
    return meta


def slice_to_dir(
    map_path: str | Path, out_dir: str | Path, chunk_width: int = 100, chunk_height: int = 100
) -> MapMetaSet:
    """Writes meta.json, one PGM per chunk and map.yaml (PGM flavour, ROS thresholds)."""
    if chunk_width < 1 or chunk_height < 1:
        raise ValueError("chunk width and height must be at least 1 pixel")
    ros_map = load_map_file(map_path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = _meta(ros_map, chunk_width, chunk_height)
    for (row, column), data in slice_chunks(ros_map, chunk_width, chunk_height).items():
        write_pgm(
            out / chunk_file(row, column),
            np.frombuffer(data, np.uint8).reshape(chunk_height, chunk_width),
            maxval=ros_map.max_brightness,
        )
    (out / META_FILE).write_text(json.dumps(meta_to_json(meta), indent=2) + "\n")
    ros = {"pgm_format": ros_map.magic}
    if not math.isnan(ros_map.resolution):
        ros.update(
            {
                "mode": ros_map.mode,
                "negate": ros_map.negate,
                "occupied_thresh": ros_map.occupied_thresh,
                "free_thresh": ros_map.free_thresh,
            }
        )
    (out / ROS_FILE).write_text(yaml.safe_dump(ros, sort_keys=False))
    return meta


def stitch_dir(work_dir: str | Path, out_path: str | Path, *, magic: str | None = None) -> Path:
    """Reads meta.json and the chunk PGMs of work_dir and writes the whole map to out_path
    (a .pgm, or a .yaml with its .pgm beside it)."""
    work = Path(work_dir)
    meta = meta_from_json(json.loads((work / META_FILE).read_text()))
    ros = yaml.safe_load((work / ROS_FILE).read_text()) if (work / ROS_FILE).exists() else {}
    negate = int(ros.get("negate", 0))
    fill = UNKNOWN if not negate else 255 - UNKNOWN
    chunks = {}
    for row in range(meta.chunk_rows):
        for column in range(meta.chunk_cols):
            path = work / chunk_file(row, column)
            if path.exists():
                chunks[(row, column)] = read_pgm(path)[0].tobytes()
    pixels = stitch(chunks, meta, fill)
    magic = magic or ros.get("pgm_format", "P5")
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() in (".yaml", ".yml"):
        if meta.resolution is None:
            raise ValueError("meta.json has no resolution/origin: write a .pgm instead")
        from mapservice.adapters.ros_map import save_ros_map

        save_ros_map(
            RosMap(
                pixels,
                meta.resolution,
                meta.origin,  # type: ignore[arg-type]
                comment=meta.comment,
                negate=negate,
                occupied_thresh=float(ros.get("occupied_thresh", 0.65)),
                free_thresh=float(ros.get("free_thresh", 0.196)),
                mode=str(ros.get("mode", "trinary")),
                magic=magic,
                max_brightness=int(meta.max_brightness),
            ),
            out,
        )
    else:
        write_pgm(out, pixels, magic=magic, comment=meta.comment, maxval=int(meta.max_brightness))
    return out


def describe(map_path: str | Path, chunk_width: int = 100, chunk_height: int = 100) -> dict:
    """What `mapservice map info` prints: size, geometry, chunk grid, pixel classes."""
    from mapservice.adapters.ros_map import FREE, OCCUPIED, classify

    ros_map = load_map_file(map_path)
    meta = _meta(ros_map, chunk_width, chunk_height)
    info = {"file": str(map_path), "pgm_format": ros_map.magic, **meta_to_json(meta)}
    if meta.resolution is not None:
        classes = classify(ros_map)
        info.update(
            {
                "mode": ros_map.mode,
                "negate": ros_map.negate,
                "occupied_thresh": ros_map.occupied_thresh,
                "free_thresh": ros_map.free_thresh,
                "size_m": [
                    round(ros_map.width * ros_map.resolution, 3),
                    round(ros_map.height * ros_map.resolution, 3),
                ],
                "free_px": int((classes == FREE).sum()),
                "occupied_px": int((classes == OCCUPIED).sum()),
                "unknown_px": int((classes < 0).sum()),
                # map_saver's 'unknown' value; a YAML's free_thresh may count it as free
                "unknown_value_px": int((ros_map.pixels == ros_map.unknown_value).sum()),
                "padding_px": meta.chunk_rows * chunk_height * meta.chunk_cols * chunk_width
                - ros_map.width * ros_map.height,
            }
        )
    return info
