"""An in-memory HistoryStore with the same semantics as ClickHouse (for pure tests).

It keeps what ClickHouse keeps: positions to the millimetre, quaternions and battery as
32-bit floats, one row per natural identity (the last write wins).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np

from ..events import ChunkUpdated, DeadLetter, Envelope, MapMetaSet, PoseReported
from ..ports import ChunkRow, Counts, PoseRow
from ..schema import SCHEMA_VERSION
from ..timetravel import ChunkState, fold_map, fold_robots


def _mm(v: float) -> float:
    return round(v * 1000) / 1000


def _f32(v: float | None) -> float | None:
    return None if v is None else float(np.float32(v))


class MemoryStore:
    def __init__(self) -> None:
        self._poses: dict[tuple[str, int], PoseRow] = {}
        self._chunks: dict[tuple[int, int, int, str], ChunkRow] = {}
        self._contents: dict[bytes, tuple[int, int, bytes]] = {}
        self._metas: dict[tuple[int, str], MapMetaSet] = {}
        self._dead: list[DeadLetter] = []
        self._lock = threading.Lock()

    def migrate(self) -> int:
        return SCHEMA_VERSION

    def append(self, events: Sequence[Envelope]) -> None:
        with self._lock:
            for e in events:
                p = e.payload
                if isinstance(p, PoseReported):
                    self._poses[(e.robot_id, e.event_time_ms)] = PoseRow(
                        e.robot_id, e.event_time_ms, *(_mm(v) for v in p.position),
                        *(_f32(v) for v in p.orientation), _f32(p.battery_level),
                        p.charging, p.loaded,
                        tuple((_mm(x), _mm(y)) for x, y in p.path) if p.path is not None else None,
                        e.receive_time_ms)
                elif isinstance(p, ChunkUpdated):
                    self._contents.setdefault(p.content_hash, (p.width, p.height, p.data))
                    key = (e.event_time_ms, p.row, p.column, e.robot_id)
                    self._chunks[key] = ChunkRow(p.row, p.column, e.event_time_ms, e.robot_id,
                                                 p.content_hash.hex(), e.receive_time_ms)
                elif isinstance(p, MapMetaSet):
                    self._metas[(e.event_time_ms, e.robot_id)] = p

    def append_dead_letters(self, records: Sequence[DeadLetter]) -> None:
        with self._lock:
            self._dead.extend(records)

    def poses(self, from_ms: int, to_ms: int, robot_id: str | None = None,
              limit: int = 100_000) -> list[PoseRow]:
        rows = [r for r in self._poses.values()
                if from_ms <= r.ts_ms < to_ms and (robot_id is None or r.robot_id == robot_id)]
        return sorted(rows, key=lambda r: (r.ts_ms, r.robot_id))[:limit]

    def poses_downsampled(self, from_ms: int, to_ms: int, step_ms: int,
                          robot_id: str | None = None, limit: int = 100_000) -> list[PoseRow]:
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        first: dict[tuple[str, int], PoseRow] = {}
        for r in self.poses(from_ms, to_ms, robot_id, limit=len(self._poses)):
            first.setdefault((r.robot_id, (r.ts_ms - from_ms) // step_ms), r)
        return sorted(first.values(), key=lambda r: (r.ts_ms, r.robot_id))[:limit]

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        rows = [r for r in self._chunks.values() if from_ms <= r.ts_ms < to_ms]
        return sorted(rows, key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))[:limit]

    def map_at(self, at_ms: int) -> list[ChunkState]:
        state = fold_map(list(self._chunks.values()), at_ms)
        return [state[k] for k in sorted(state)]

    def robots_at(self, at_ms: int) -> list[PoseRow]:
        state = fold_robots(list(self._poses.values()), at_ms)
        return [state[k] for k in sorted(state)]

    def build_snapshots(self, up_to_ms: int) -> int:
        return 0  # folds the whole history on every read: nothing to snapshot

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        return self._contents.get(content_hash)

    def chunk_contents(self, hashes: Sequence[bytes]) -> dict[bytes, tuple[int, int, bytes]]:
        return {h: self._contents[h] for h in set(hashes) if h in self._contents}

    def latest_meta(self) -> MapMetaSet | None:
        if not self._metas:
            return None
        return self._metas[max(self._metas)]

    def counts(self) -> Counts:
        return Counts(len(self._poses), len(self._chunks), len(self._contents), len(self._dead))

    def close(self) -> None:
        pass
