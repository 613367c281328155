"""2019 wire messages for the decoder tests: listing 14 (chunk) and 16 (pose) documents
at a fixed instant, with any field replaced or dropped."""

from __future__ import annotations

import json

from mapservice.core.events import MapMetaSet
from mapservice.core.wire2019 import Limits, encode_pixels, format_timestamp
from tests.fixtures.listings_2019 import DROP as DROP
from tests.fixtures.listings_2019 import listing_14, listing_16

NOW = 1_795_255_200_000  # same instant as conftest.NOW_MS: 2026-11-21T10:00:00Z
DAY = 86_400_000
SKEW = Limits().max_future_skew_ms
RETENTION = Limits().retention_ms


b64z = encode_pixels


def stamp(offset_ms: int = 0) -> str:
    """The 2019 timestamp text of NOW + offset_ms."""
    return format_timestamp(NOW + offset_ms)


def chunk_json(**overrides) -> bytes:
    """A valid listing-14 chunk message, fields replaced by `overrides` (DROP: left out)."""
    return json.dumps(listing_14(stamp(), **overrides)).encode()


def pose_json(**overrides) -> bytes:
    """A valid listing-16 pose message, fields replaced by `overrides` (DROP: left out)."""
    return json.dumps(listing_16(stamp(), **overrides)).encode()


def at_pose(x=10, y=20, z=0, q=(0, 0, 0, 1)) -> dict:
    return {"position": {"x": x, "y": y, "z": z}, "orientation": dict(zip("xyzw", q))}


META_4x5 = MapMetaSet(
    width=500, height=400, chunk_width=100, chunk_height=100, chunk_rows=4, chunk_cols=5
)
