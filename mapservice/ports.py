"""The ports: small interfaces the components depend on. Adapters live in `adapters/`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

import msgspec

from .events import DeadLetter, Envelope, MapMetaSet

if TYPE_CHECKING:
    from .timetravel import ChunkState


class Clock(Protocol):
    def now_ms(self) -> int:
        """Milliseconds since the epoch, UTC."""


class EventPublisher(Protocol):
    """Appends records to a durable log; `on_done(error)` fires once the log has them."""

    def publish(
        self, topic: str, key: bytes, value: bytes, on_done: Callable[[Exception | None], None]
    ) -> None: ...

    def poll(self, timeout: float) -> None:
        """Runs pending delivery callbacks."""

    def flush(self, timeout: float) -> int:
        """Waits for outstanding records; returns how many are still undelivered."""


class PoseRow(msgspec.Struct, frozen=True, array_like=True):
    robot_id: str
    ts_ms: int
    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float
    battery_level: float | None
    charging: bool | str | None
    loaded: bool | str | None
    path: tuple[tuple[float, float], ...] | None
    receive_time_ms: int


class ChunkRow(msgspec.Struct, frozen=True, array_like=True):
    row: int
    column: int
    ts_ms: int
    robot_id: str
    content_hash: str  # hex
    receive_time_ms: int


class Counts(msgspec.Struct, frozen=True):
    poses: int
    chunk_events: int
    chunk_contents: int
    dead_letters: int


class HistoryStore(Protocol):
    """The seven-day history. Appends are idempotent on each event's natural identity."""

    def migrate(self) -> int:
        """Creates or upgrades the schema; returns the schema version. Safe to repeat."""

    def append(self, events: Sequence[Envelope]) -> None: ...

    def append_dead_letters(self, records: Sequence[DeadLetter]) -> None: ...

    def poses(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 100_000
    ) -> list[PoseRow]:
        """Poses with from_ms <= event time < to_ms, ordered by time then robot."""

    def poses_downsampled(
        self, from_ms: int, to_ms: int, step_ms: int, robot_id: str | None = None,
        limit: int = 100_000,
    ) -> list[PoseRow]:
        """Per robot, its first pose in each step [from_ms + k*step_ms, from_ms + (k+1)*step_ms)
        of from_ms <= event time < to_ms: at most one frame per robot per step, ordered by
        time then robot (a replay's poses at a coarser rate)."""

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        """Chunk writes with from_ms <= event time < to_ms, in event-time order."""

    def map_at(self, at_ms: int) -> list["ChunkState"]:
        """Per chunk, the write with the greatest (event time, robot id) at or before `at_ms`."""

    def robots_at(self, at_ms: int) -> list[PoseRow]:
        """Per robot, its pose with the greatest event time at or before `at_ms`."""

    def build_snapshots(self, up_to_ms: int) -> int:
        """Builds the snapshots due up to `up_to_ms`; returns how many were built."""

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        """(width, height, zlib pixels) of a content hash, if stored."""

    def chunk_contents(self, hashes: Sequence[bytes]) -> dict[bytes, tuple[int, int, bytes]]:
        """Many content hashes at once; unknown ones are left out."""

    def latest_meta(self) -> MapMetaSet | None: ...

    def counts(self) -> Counts: ...

    def close(self) -> None: ...
