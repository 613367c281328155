"""Chunks to pictures: stitch the map at an instant, encode PNGs (numpy + Pillow)."""

from __future__ import annotations

import io
import zlib
from collections.abc import Iterable

import numpy as np
from PIL import Image

from mapservice.core.events import MapMetaSet
from mapservice.core.ports import ChunkState

UNKNOWN = 205  # the pixel of an unknown cell, as ROS map_saver writes it (negate: 0)


def chunk_pixels(width: int, height: int, zlib_pixels: bytes) -> np.ndarray:
    return np.frombuffer(zlib.decompress(zlib_pixels), dtype=np.uint8).reshape(height, width)


def stitch(
    meta: MapMetaSet, chunks: Iterable[ChunkState], contents: dict[bytes, tuple[int, int, bytes]]
) -> np.ndarray:
    """The whole map as one image (row 0 at the top, as in the PGM); unknown where unwritten."""
    cw, ch = meta.chunk_width, meta.chunk_height
    canvas = np.full((meta.chunk_rows * ch, meta.chunk_cols * cw), UNKNOWN, dtype=np.uint8)
    for c in chunks:
        found = contents.get(bytes.fromhex(c.content_hash))
        if found is None or not (0 <= c.row < meta.chunk_rows and 0 <= c.column < meta.chunk_cols):
            continue
        w, h, data = found
        if (w, h) != (cw, ch):
            continue  # written under another chunk size; not part of this map's grid
        canvas[c.row * ch : (c.row + 1) * ch, c.column * cw : (c.column + 1) * cw] = chunk_pixels(
            w, h, data
        )
    return canvas[: meta.height, : meta.width]


def png(pixels: np.ndarray, scale: float = 1.0) -> bytes:
    """A PNG of grey pixels (rows x columns) or RGBA ones (rows x columns x 4)."""
    image = Image.fromarray(pixels, mode="L" if pixels.ndim == 2 else "RGBA")
    if scale != 1.0:
        size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
        image = image.resize(size, Image.Resampling.NEAREST)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=False)
    return out.getvalue()
