"""2019 wire messages for the decoder tests: listing 14 (chunk) and 16 (pose) documents
at a fixed instant, with any field replaced or dropped."""

from __future__ import annotations

import base64
import json
import zlib

from mapservice.core.events import MapMetaSet
from mapservice.core.wire2019 import Limits, format_timestamp

NOW = 1_795_255_200_000  # same instant as conftest.NOW_MS: 2026-11-21T10:00:00Z
DAY = 86_400_000
SKEW = Limits().max_future_skew_ms
RETENTION = Limits().retention_ms


def b64z(raw: bytes) -> str:
    return base64.b64encode(zlib.compress(raw)).decode()


def stamp(offset_ms: int = 0) -> str:
    """The 2019 timestamp text of NOW + offset_ms."""
    return format_timestamp(NOW + offset_ms)


def chunk_json(**overrides) -> bytes:
    """A valid listing-14 chunk message, fields replaced by `overrides` (DROP: left out)."""
    doc = {
        "pgmB64compressedData": b64z(bytes(10_000)),
        "row": 3,
        "column": 2,
        "timestamp": stamp(),
        "robotId": "lkjlkj",
    }
    doc.update(overrides)
    return json.dumps({k: v for k, v in doc.items() if v is not DROP}).encode()


def pose_json(**overrides) -> bytes:
    """A valid listing-16 pose message, fields replaced by `overrides` (DROP: left out)."""
    doc = {
        "robotId": "blabla",
        "timestamp": stamp(),
        "pose": {
            "position": {"x": 10, "y": 20, "z": 0},
            "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
        },
        "status": {"battery": {"battery_level": 3, "charging": "sdf"}, "loaded": "dfs"},
    }
    doc.update(overrides)
    return json.dumps({k: v for k, v in doc.items() if v is not DROP}).encode()


def at_pose(x=10, y=20, z=0, q=(0, 0, 0, 1)) -> dict:
    return {"position": {"x": x, "y": y, "z": z}, "orientation": dict(zip("xyzw", q))}


DROP = object()  # as an override: the field is left out
META_4x5 = MapMetaSet(
    width=500, height=400, chunk_width=100, chunk_height=100, chunk_rows=4, chunk_cols=5
)
