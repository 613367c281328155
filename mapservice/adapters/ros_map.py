"""ROS occupancy-grid maps (PGM + YAML) and their cut into chunks.

Pillow decodes the pixels of both PGM flavours (P2 plain, P5 binary); the header is read
here only to keep what Pillow drops (the comment the 2019 meta.json carries, the maxval)
and to write the file back byte for byte.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from mapservice.core.events import MapMetaSet
from mapservice.core.render import UNKNOWN

FREE, OCCUPIED, UNKNOWN_CLASS = 0, 100, -1  # nav_msgs/OccupancyGrid values


@dataclass(frozen=True)
class RosMap:
    pixels: np.ndarray  # uint8, shape (height, width), row 0 at the top as in the PGM
    resolution: float
    origin: tuple[float, float, float]
    comment: str = ""
    negate: int = 0
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    mode: str = "trinary"
    magic: str = "P5"  # P5 binary or P2 plain, as read
    max_brightness: int = 255

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    @property
    def unknown_value(self) -> int:
        """The pixel value map_saver writes for 'unknown' under this map's negate flag."""
        return UNKNOWN if not self.negate else 255 - UNKNOWN

    def with_pixels(self, pixels: np.ndarray) -> RosMap:
        return replace(self, pixels=pixels)


@dataclass(frozen=True)
class PgmHeader:
    magic: str
    width: int
    height: int
    maxval: int
    comments: tuple[str, ...]  # whole lines with their '#' (as 2019 meta.json keeps them)


_TOKEN = re.compile(rb"\s*(#[^\n]*\n|\S+)")


def read_pgm_header(data: bytes) -> PgmHeader:
    """Magic, size, maxval and comment lines of a P2 or P5 file."""
    tokens: list[bytes] = []
    comments: list[str] = []
    pos = 0
    while len(tokens) < 4:
        m = _TOKEN.match(data, pos)
        if m is None:
            raise ValueError("truncated PGM header")
        pos = m.end()
        tok = m.group(1)
        if tok.startswith(b"#"):
            comments.append(tok.rstrip(b"\r\n").decode("latin-1"))
        else:
            tokens.append(tok)
    magic = tokens[0].decode("latin-1")
    if magic not in ("P2", "P5"):
        raise ValueError(f"not a greyscale PGM (magic {magic!r}; expected P2 or P5)")
    width, height, maxval = (int(t) for t in tokens[1:4])
    if not 0 < maxval <= 255:
        raise ValueError(
            f"PGM maxval {maxval} is not supported (ROS maps are 8-bit, maxval <= 255)"
        )
    return PgmHeader(magic, width, height, maxval, tuple(comments))


def read_pgm(path: str | Path) -> tuple[np.ndarray, PgmHeader]:
    """Pixels (as stored, 0..maxval) and header of a PGM file."""
    path = Path(path)
    header = read_pgm_header(path.read_bytes()[:4096])
    with Image.open(path) as img:
        pixels = np.asarray(img.convert("L"), dtype=np.uint8)
    if header.maxval != 255:
        # Pillow scales to 0..255; the map's own values are what chunks must carry.
        pixels = np.rint(pixels.astype(np.float64) * header.maxval / 255).astype(np.uint8)
    return pixels, header


def write_pgm(
    path: str | Path, pixels: np.ndarray, *, magic: str = "P5", comment: str = "", maxval: int = 255
) -> None:
    """Writes P5 or P2 in the layout GIMP and map_saver use (one header item per line).

    Pillow writes P5 only and without a comment, so the header is written here.
    """
    pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
    height, width = pixels.shape
    comments = [c if c.startswith("#") else f"# {c}" for c in comment.splitlines()]
    lines = [magic] + comments + [f"{width} {height}", str(maxval)]
    head = ("\n".join(lines) + "\n").encode("latin-1")
    if magic == "P5":
        body = pixels.tobytes()
    elif magic == "P2":
        body = "".join(" ".join(map(str, row)) + "\n" for row in pixels.tolist()).encode()
    else:
        raise ValueError(f"magic must be P2 or P5, not {magic!r}")
    Path(path).write_bytes(head + body)


def load_ros_map(yaml_path: str | Path) -> RosMap:
    """Loads a map_server YAML and its image (paths relative to the YAML file)."""
    yaml_path = Path(yaml_path)
    doc = yaml.safe_load(yaml_path.read_text())
    if not isinstance(doc, dict) or "image" not in doc or "resolution" not in doc:
        raise ValueError(f"{yaml_path}: a ROS map YAML needs at least 'image' and 'resolution'")
    image_path = (yaml_path.parent / doc["image"]).resolve()
    if image_path.suffix.lower() in (".pgm", ".pnm"):
        pixels, header = read_pgm(image_path)
        comment, magic, maxval = "\n".join(header.comments), header.magic, header.maxval
    else:  # map_server also takes PNG and other images Pillow reads
        with Image.open(image_path) as img:
            pixels = np.asarray(img.convert("L"), dtype=np.uint8)
        comment, magic, maxval = "", "P5", 255
    origin = tuple(float(v) for v in doc.get("origin", (0.0, 0.0, 0.0)))
    return RosMap(
        pixels,
        float(doc["resolution"]),
        origin,  # type: ignore[arg-type]
        comment=comment,
        negate=int(doc.get("negate", 0)),
        occupied_thresh=float(doc.get("occupied_thresh", 0.65)),
        free_thresh=float(doc.get("free_thresh", 0.196)),
        mode=str(doc.get("mode", "trinary")),
        magic=magic,
        max_brightness=maxval,
    )


def save_ros_map(ros_map: RosMap, yaml_path: str | Path, image_name: str | None = None) -> Path:
    """Writes the PGM and a map_server YAML beside it (image path relative to the YAML)."""
    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    write_pgm(
        yaml_path.parent / image_name,
        ros_map.pixels,
        magic=ros_map.magic,
        comment=ros_map.comment,
        maxval=ros_map.max_brightness,
    )
    doc = {
        "image": image_name,
        "mode": ros_map.mode,
        "resolution": ros_map.resolution,
        "origin": list(ros_map.origin),
        "negate": ros_map.negate,
        "occupied_thresh": ros_map.occupied_thresh,
        "free_thresh": ros_map.free_thresh,
    }
    yaml_path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return yaml_path


def classify(ros_map: RosMap) -> np.ndarray:
    """Per pixel FREE (0), OCCUPIED (100) or UNKNOWN_CLASS (-1), as map_server reads it
    in trinary mode: occ = 1 - value/255 (value/255 with negate), then the thresholds."""
    shade = ros_map.pixels.astype(np.float32) / max(ros_map.max_brightness, 1)
    occ = shade if ros_map.negate else 1.0 - shade
    out = np.full(ros_map.pixels.shape, UNKNOWN_CLASS, dtype=np.int8)
    out[occ > ros_map.occupied_thresh] = OCCUPIED
    out[occ < ros_map.free_thresh] = FREE
    return out


def drivable(ros_map: RosMap) -> np.ndarray:
    """Pixels a robot may stand on: free by the thresholds and not the 'unknown' fill value.

    The fill value is excluded on its own because a YAML's free_thresh can make it free
    (depot.yaml: free_thresh 0.25 puts 205, occ 0.196, on the free side).
    """
    return (classify(ros_map) == FREE) & (ros_map.pixels != ros_map.unknown_value)


def meta_for(ros_map: RosMap, chunk_width: int = 100, chunk_height: int = 100) -> MapMetaSet:
    rows = -(-ros_map.height // chunk_height)
    cols = -(-ros_map.width // chunk_width)
    return MapMetaSet(
        width=ros_map.width,
        height=ros_map.height,
        chunk_width=chunk_width,
        chunk_height=chunk_height,
        chunk_rows=rows,
        chunk_cols=cols,
        comment=ros_map.comment,
        max_brightness=str(ros_map.max_brightness),
        resolution=ros_map.resolution,
        origin=ros_map.origin,
    )


def slice_chunks(
    ros_map: RosMap, chunk_width: int = 100, chunk_height: int = 100
) -> dict[tuple[int, int], bytes]:
    """(row, column) -> chunk pixels; the map is padded with 'unknown' to whole chunks."""
    meta = meta_for(ros_map, chunk_width, chunk_height)
    padded = np.full(
        (meta.chunk_rows * chunk_height, meta.chunk_cols * chunk_width),
        ros_map.unknown_value,
        dtype=np.uint8,
    )
    padded[: ros_map.height, : ros_map.width] = ros_map.pixels
    return {
        (r, c): padded[
            r * chunk_height : (r + 1) * chunk_height, c * chunk_width : (c + 1) * chunk_width
        ].tobytes()
        for r in range(meta.chunk_rows)
        for c in range(meta.chunk_cols)
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
