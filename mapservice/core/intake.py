"""The one door for 2019 writes: every channel that puts a 2019 message into the log (the
MQTT gateway, the 2019 REST API, `up`'s start-up map upload, `mapservice map upload`)
hands its wire bytes to an `Intake`, which answers an `Envelope` to publish or a
`Rejection` whose reason is the same whichever channel it came by.

Pure: the limits come from the settings through `Intake.from_settings` (read by
attribute, so the core imports no settings), the map meta narrows them once known.
"""

from __future__ import annotations

from typing import Annotated, Protocol

import msgspec

from mapservice.core.events import Envelope, MapMetaSet
from mapservice.core.wire2019 import (
    Limits,
    Reason,
    Rejection,
    decode,
    decode_chunk_create,
    decode_coordinates,
    oversized,
)

# The meta's bounds: a chunk is at most 4096 px a side (what the history stores per
# chunk), a map and its grid at most 65,535 of a kind (UInt16 columns).
MAX_CHUNK_SIDE = 4096
MAX_MAP_SIDE = 65_535


class IntakeSettings(Protocol):
    """The settings an intake is built from (`mapservice.settings.Settings` has them)."""

    @property
    def chunk_width(self) -> int: ...
    @property
    def chunk_height(self) -> int: ...
    @property
    def max_grid(self) -> int: ...
    @property
    def max_message_bytes(self) -> int: ...
    @property
    def max_future_skew_s(self) -> float: ...
    @property
    def retention_ms(self) -> int: ...


class MetaDoc(msgspec.Struct):
    """meta.json (listing 8/9) as a robot posts it; ROS resolution/origin are optional."""

    width: int
    height: int
    CHUNK_WIDTH: int
    CHUNK_HEIGHT: int
    CHUNK_ROWS: int
    CHUNK_COLS: int
    comment: str = ""
    max_brightness: str | int = "255"
    resolution: float | None = None
    origin: Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)] | None = None


_meta_decoder = msgspec.json.Decoder(MetaDoc)


def refusal_text(rejection: Rejection) -> str:
    """A refusal as every channel words it: the reason code first, then what is wrong."""
    return f"{rejection.reason.value}: {rejection.detail}"


def split_refusal(text: str) -> tuple[Reason, str] | None:
    """`refusal_text`'s inverse: (reason, detail), or None for a text naming no reason."""
    code, _, detail = text.partition(": ")
    try:
        return Reason(code), detail
    except ValueError:
        return None


class Intake:
    """Validation and limits of every 2019 write, built once from the settings."""

    def __init__(self, limits: Limits | None = None) -> None:
        self.limits = limits or Limits()

    @classmethod
    def from_settings(cls, settings: IntakeSettings) -> Intake:
        return cls(
            Limits(
                chunk_width=settings.chunk_width,
                chunk_height=settings.chunk_height,
                chunk_rows=settings.max_grid,
                chunk_cols=settings.max_grid,
                max_message_bytes=settings.max_message_bytes,
                max_future_skew_ms=int(settings.max_future_skew_s * 1000),
                retention_ms=settings.retention_ms,
            )
        )

    def with_meta(self, meta: MapMetaSet | None) -> Intake:
        """This intake with the map meta's chunk size and grid (unchanged for None)."""
        return self if meta is None else Intake(self.limits.with_meta(meta))

    def chunk(
        self, data: bytes, receive_ms: int, topic_robot_id: str | None = None
    ) -> Envelope | Rejection:
        """An `iot/chunks/create` message (listing 14) or a POST /chunks body (listing 10)."""
        return decode_chunk_create(data, receive_ms, self.limits, topic_robot_id)

    def coordinates(self, robot_id: str, data: bytes, receive_ms: int) -> Envelope | Rejection:
        """An `iot/coordinates/{robotId}` message (listing 16)."""
        return decode_coordinates(robot_id, data, receive_ms, self.limits)

    def map_meta(self, data: bytes) -> MapMetaSet | Rejection:
        """A meta.json (listing 8): the map's meta (its writer's channel names the robot)."""
        if len(data) > self.limits.max_message_bytes:
            return oversized(len(data), self.limits)
        doc = decode(_meta_decoder, data, "meta.json")
        if isinstance(doc, Rejection):
            return doc
        sizes = {
            "width": doc.width,
            "height": doc.height,
            "CHUNK_WIDTH": doc.CHUNK_WIDTH,
            "CHUNK_HEIGHT": doc.CHUNK_HEIGHT,
            "CHUNK_ROWS": doc.CHUNK_ROWS,
            "CHUNK_COLS": doc.CHUNK_COLS,
        }
        for name, value in sizes.items():
            high = MAX_CHUNK_SIDE if name in ("CHUNK_WIDTH", "CHUNK_HEIGHT") else MAX_MAP_SIDE
            if not 1 <= value <= high:
                return Rejection(
                    Reason.OUT_OF_RANGE, f"meta.json: {name} = {value} is outside 1..{high}"
                )
        if (
            doc.CHUNK_COLS * doc.CHUNK_WIDTH < doc.width
            or doc.CHUNK_ROWS * doc.CHUNK_HEIGHT < doc.height
        ):
            return Rejection(
                Reason.GRID_SHORT_OF_MAP,
                f"meta.json: {doc.CHUNK_ROWS} x {doc.CHUNK_COLS} chunks of "
                f"{doc.CHUNK_WIDTH} x {doc.CHUNK_HEIGHT} do not cover "
                f"{doc.width} x {doc.height} pixels",
            )
        if doc.resolution is not None and not 0 < doc.resolution < 1e6:
            return Rejection(
                Reason.OUT_OF_RANGE,
                f"meta.json: resolution {doc.resolution} m per pixel is not above 0 and below 1e6",
            )
        return MapMetaSet.from_2019(msgspec.to_builtins(doc))
