"""The robot agent's local map and what changed in it (pure): the map pixels, per chunk what
the service is known to hold, and the 2019 REST chunk documents."""

from __future__ import annotations

import base64
import zlib
from dataclasses import dataclass, field

import msgspec
import numpy as np

from mapservice.adapters.ros_map import RosMap, meta_for
from mapservice.core.events import MapMetaSet
from mapservice.core.wire2019 import content_hash, encode_chunk_create, format_timestamp

from .chunks import chunk_pixels, paste_chunk


@dataclass
class LocalMap:
    """The robot's map pixels and, per chunk, what the service is known to hold."""

    pixels: np.ndarray
    meta: MapMetaSet
    fill: int
    known: dict[tuple[int, int], tuple[bytes, bytes]] = field(default_factory=dict)  # hash, pixels

    @classmethod
    def of(cls, ros_map: RosMap, chunk_width: int = 100, chunk_height: int = 100) -> LocalMap:
        local = cls(
            ros_map.pixels.copy(),
            meta_for(ros_map, chunk_width, chunk_height),
            ros_map.unknown_value,
        )
        local.mark_all_known()
        return local

    def chunk(self, row: int, column: int) -> bytes:
        return chunk_pixels(self.pixels, self.meta, row, column, self.fill)

    def cells(self):
        return ((r, c) for r in range(self.meta.chunk_rows) for c in range(self.meta.chunk_cols))

    def mark_all_known(self) -> None:
        for rc in self.cells():
            data = self.chunk(*rc)
            self.known[rc] = (content_hash(data), data)

    def changes(self, pixels: np.ndarray, threshold: float = 0.0) -> list[tuple[int, int, bytes]]:
        """Chunks of `pixels` whose hash differs from the known one and of which more than
        `threshold` (a fraction of the chunk's pixels) changed; they become the known ones."""
        self.pixels = pixels
        out = []
        for rc in self.cells():
            data = self.chunk(*rc)
            digest = content_hash(data)
            known_hash, known = self.known.get(rc, (b"", b""))
            if digest == known_hash:
                continue
            if known and len(known) == len(data):
                changed = np.count_nonzero(
                    np.frombuffer(data, np.uint8) != np.frombuffer(known, np.uint8)
                )
                if changed <= threshold * len(data):
                    continue  # small noise: keep comparing against what the service holds
            self.known[rc] = (digest, data)
            out.append((*rc, data))
        return out

    def integrate(self, row: int, column: int, data: bytes) -> bool:
        """Writes a chunk from the service into the map; False when it held it already."""
        if not (0 <= row < self.meta.chunk_rows and 0 <= column < self.meta.chunk_cols):
            return False
        if len(data) != self.meta.chunk_width * self.meta.chunk_height:
            raise ValueError(f"chunk ({row}, {column}) has {len(data)} bytes")
        digest = content_hash(data)
        self.known[(row, column)] = (digest, data)
        if self.chunk(row, column) == data:
            return False
        pixels = self.pixels.copy()
        paste_chunk(pixels, self.meta, row, column, data)
        self.pixels = pixels
        return True


def decode_chunk_doc(doc: dict) -> tuple[int, int, bytes]:
    """(row, column, pixels) of a chunk as the REST API returns it (listing 13)."""
    kind = doc.get("type", "pgm_base64_compressed")
    if kind != "pgm_base64_compressed":
        raise ValueError(f"chunk type {kind!r}; ask for pgm_base64_compressed")
    raw = doc.get("chunk") or doc.get("pgmB64compressedData")
    if raw is None:
        raise ValueError("chunk document has no 'chunk' field")
    return int(doc["row"]), int(doc["column"]), zlib.decompress(base64.b64decode(raw))


def chunk_body(row: int, column: int, data: bytes, robot_id: str, t_ms: int) -> dict:
    """Listing 10: the JSON a robot POSTs to /api/chunk-service/chunks."""
    return msgspec.json.decode(
        encode_chunk_create(row, column, data, format_timestamp(t_ms), robot_id)
    )


def compatible(local: MapMetaSet, remote: MapMetaSet) -> bool:
    return (local.width, local.height, local.chunk_width, local.chunk_height) == (
        remote.width,
        remote.height,
        remote.chunk_width,
        remote.chunk_height,
    )
