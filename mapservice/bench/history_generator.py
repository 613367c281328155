"""The history loader's workload as numpy columns: the 2019 load test's (and `loadgen.py`'s).

Every robot reports one pose a second while driving a 1 m circle, and every fifth pose it
sends one chunk: a real chunk of the map re-sent at a random (row, column) of the grid. A
small share of the chunk writes carry changed pixels (a painted rectangle), so
`chunk_contents` holds more than the map's own chunks. The rows come one UTC day at a time
(one part per day partition, bounded memory), with the values `ClickHouseStore.append`
would store for the same events.

Every circle lies on free pixels: a robot's centre is a free cell of
`mapfile.free_cells_metres` whose whole 1 m ring (every pixel the circle can touch, after
rounding to millimetres) is free, so every stored pose is on a free cell of the map.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import date

import numpy as np

from mapservice.adapters.ros_map import RosMap, free_cells_metres, meta_for, slice_chunks
from mapservice.core.events import MapMetaSet
from mapservice.core.wire2019 import content_hash

DAY_MS = 86_400_000
POSE_PERIOD_MS = 1000
CHUNK_EVERY = 5  # poses per chunk, as in the 2019 load test
RADIUS_M = 1.0  # the circle each robot drives (loadgen.py)
ANGULAR_SPEED = 0.2  # rad/s (loadgen.py)


def circle_centres(ros_map: RosMap, radius_m: float = RADIUS_M) -> np.ndarray:
    """Free cells (x, y metres, as `free_cells_metres`) whose whole circle is on free pixels.

    A point at distance r from a pixel centre lies in a pixel whose centre is within
    r +- (half a pixel diagonal + millimetre rounding) of it, so every pixel in that ring
    must be free.
    """
    free = free_cells_metres(ros_map)
    res = ros_map.resolution
    ox, oy, _ = ros_map.origin
    px = np.floor((free[:, 0] - ox) / res).astype(np.int64)
    py = np.floor(ros_map.height - (free[:, 1] - oy) / res).astype(np.int64)
    r = radius_m / res
    slack = math.sqrt(0.5) + 0.001 / res + 0.01
    reach = math.ceil(r + slack)
    dy, dx = np.mgrid[-reach : reach + 1, -reach : reach + 1]
    ring = np.abs(np.hypot(dx, dy) - r) <= slack
    ys = py[:, None] + dy[ring][None, :]
    xs = px[:, None] + dx[ring][None, :]
    inside = (ys >= 0) & (ys < ros_map.height) & (xs >= 0) & (xs < ros_map.width)
    values = ros_map.pixels[np.clip(ys, 0, ros_map.height - 1), np.clip(xs, 0, ros_map.width - 1)]
    ok = inside.all(axis=1) & (values >= 250).all(axis=1)
    return free[ok]


def pixel_of(ros_map: RosMap, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(image row, image column) of world points, the inverse of `free_cells_metres`."""
    ox, oy, _ = ros_map.origin
    col = np.floor((np.asarray(x_m) - ox) / ros_map.resolution).astype(np.int64)
    row = np.floor(ros_map.height - (np.asarray(y_m) - oy) / ros_map.resolution).astype(np.int64)
    return row, col


def grid_meta(
    ros_map: RosMap, rows: int | None = None, cols: int | None = None, comment: str = ""
) -> MapMetaSet:
    """The map's own chunk grid, or a `rows` x `cols` grid of 100 x 100 chunks around it."""
    meta = meta_for(ros_map)
    if rows is None and cols is None:
        return meta
    rows = rows or meta.chunk_rows
    cols = cols or meta.chunk_cols
    return MapMetaSet(
        width=cols * meta.chunk_width,
        height=rows * meta.chunk_height,
        chunk_width=meta.chunk_width,
        chunk_height=meta.chunk_height,
        chunk_rows=rows,
        chunk_cols=cols,
        comment=comment,
        resolution=meta.resolution,
        origin=meta.origin,
    )


@dataclass
class Block:
    """One day's generated rows, column by column."""

    day: int  # days since the epoch (UTC)
    poses: list
    chunks: list
    contents: list
    n_poses: int
    n_chunks: int


class HistoryGenerator:
    """Deterministic (per seed and window) numpy columns of the 2019 workload."""

    def __init__(
        self,
        ros_map: RosMap,
        robots: int,
        start_ms: int,
        end_ms: int,
        *,
        meta: MapMetaSet,
        seed: int = 7,
        change_prob: float = 0.01,
        prefix: str = "robot",
    ) -> None:
        if start_ms % POSE_PERIOD_MS:
            raise ValueError("start_ms must be a whole second")
        self.ros_map = ros_map
        self.meta = meta
        self.start_ms = start_ms
        self.seconds = max(0, (end_ms - start_ms) // POSE_PERIOD_MS)
        self.end_ms = start_ms + self.seconds * POSE_PERIOD_MS
        self.seed = seed
        self.change_prob = change_prob
        self.robot_ids = [f"{prefix}-{i:04d}" for i in range(robots)]
        centres = circle_centres(ros_map)
        if len(centres) == 0:
            raise ValueError("the map has no free circle of 1 m for a robot to drive")
        picks = np.random.default_rng(seed).integers(0, len(centres), size=max(robots, 1))
        self.centres = centres[picks][:robots]
        # Robots are spread evenly over each second, as in loadgen.py.
        self.offsets = (np.arange(robots, dtype=np.int64) * POSE_PERIOD_MS) // max(robots, 1)
        # The map's chunks (with repeats, like loadgen's random.choice over them).
        tiles = list(slice_chunks(ros_map, meta.chunk_width, meta.chunk_height).values())
        self._pixels: list[bytes] = []
        self._hashes: list[bytes] = []
        self._zlib: list[bytes] = []
        index: dict[bytes, int] = {}
        self.tile_content = np.empty(len(tiles), dtype=np.int64)
        for t, pixels in enumerate(tiles):
            h = content_hash(pixels)
            if h not in index:
                index[h] = self._add_content(h, pixels)
            self.tile_content[t] = index[h]

    def _add_content(self, h: bytes, pixels: bytes) -> int:
        self._pixels.append(pixels)
        self._hashes.append(h)
        self._zlib.append(zlib.compress(pixels))
        return len(self._hashes) - 1

    @property
    def distinct_contents(self) -> int:
        return len(set(self._hashes))

    def days(self) -> Iterator[tuple[int, int]]:
        """(first second, end second) index ranges, one per UTC day of the window."""
        k = 0
        while k < self.seconds:
            t = self.start_ms + k * POSE_PERIOD_MS
            next_midnight = (t // DAY_MS + 1) * DAY_MS
            k_end = min(self.seconds, (next_midnight - self.start_ms) // POSE_PERIOD_MS)
            yield k, k_end
            k = k_end

    def block(self, k_lo: int, k_hi: int) -> Block:
        """Rows for seconds [k_lo, k_hi) of the window (all inside one UTC day)."""
        n_robots = len(self.robot_ids)
        rng = np.random.default_rng([self.seed, self.start_ms // 1000, k_lo])
        day = (self.start_ms + k_lo * POSE_PERIOD_MS) // DAY_MS
        k = np.arange(k_lo, k_hi, dtype=np.int64)
        robot = np.arange(n_robots, dtype=np.int64)
        # Robot clocks are not perfectly periodic: up to 50 ms of jitter, kept inside the
        # second (so a day's rows stay in that day's partition).
        jitter = rng.integers(0, 50, size=(n_robots, len(k)))
        ts = self.start_ms + k[None, :] * POSE_PERIOD_MS + self.offsets[:, None] + jitter
        ts = np.minimum(ts, self.start_ms + (k[None, :] + 1) * POSE_PERIOD_MS - 1)
        poses = self._poses(ts, robot, rng)
        # Every fifth pose (pose count % 5 == 0) comes with a chunk at the same instant.
        sel = (k + 1) % CHUNK_EVERY == 0
        chunks, contents = self._chunks(ts[:, sel], robot, day, rng)
        return Block(day, poses, chunks, contents, ts.size, ts[:, sel].size)

    def _poses(self, ts: np.ndarray, robot: np.ndarray, rng: np.random.Generator) -> list:
        n = ts.size
        t_s = ts / 1000.0
        angle = t_s * ANGULAR_SPEED + robot[:, None]
        x = self.centres[:, 0:1] + RADIUS_M * np.cos(angle)
        y = self.centres[:, 1:2] + RADIUS_M * np.sin(angle)
        yaw = angle + math.pi / 2
        battery = np.round(100.0 - np.mod(t_s / 60.0 + robot[:, None], 100.0), 1)
        loaded = (robot[:, None] + ts // 60_000) % 2 == 0
        flag = np.array(["false", "true"], dtype=object)
        ids = np.array(self.robot_ids, dtype=object)
        empty: list = []
        return [
            np.repeat(ids, ts.shape[1]),
            ts.ravel().tolist(),  # DateTime64 takes Python ints (epoch ms)
            np.rint(x * 1000).astype(np.int32).ravel(),
            np.rint(y * 1000).astype(np.int32).ravel(),
            np.zeros(n, dtype=np.int32),
            np.zeros(n, dtype=np.float32),
            np.zeros(n, dtype=np.float32),
            np.sin(yaw / 2).astype(np.float32).ravel(),
            np.cos(yaw / 2).astype(np.float32).ravel(),
            battery.astype(np.float32).ravel(),
            flag[(battery < 20).astype(np.int64).ravel()],
            flag[loaded.astype(np.int64).ravel()],
            np.zeros(n, dtype=bool),
            [empty] * n,
            [empty] * n,
            rng.integers(15, 120, size=n, dtype=np.int32),
        ]

    def _variant(self, base: int, rng: np.random.Generator) -> int:
        """A new content: a base chunk with a rectangle painted free or occupied."""
        w, h = self.meta.chunk_width, self.meta.chunk_height
        pixels = np.frombuffer(self._pixels[base], dtype=np.uint8).reshape(h, w).copy()
        rh, rw = rng.integers(4, 31, size=2)
        y0, x0 = rng.integers(0, h - rh + 1), rng.integers(0, w - rw + 1)
        pixels[y0 : y0 + rh, x0 : x0 + rw] = rng.choice([0, 254])
        raw = pixels.tobytes()
        return self._add_content(content_hash(raw), raw)

    def _chunks(
        self, ts: np.ndarray, robot: np.ndarray, day: int, rng: np.random.Generator
    ) -> tuple[list, list]:
        n = ts.size
        rows = rng.integers(0, self.meta.chunk_rows, size=n).astype(np.uint16)
        cols = rng.integers(0, self.meta.chunk_cols, size=n).astype(np.uint16)
        content = self.tile_content[rng.integers(0, len(self.tile_content), size=n)]
        changed = np.nonzero(rng.random(n) < self.change_prob)[0]
        for j in changed:
            content[j] = self._variant(int(content[j]), rng)
        hashes = self._hashes
        ids = np.array(self.robot_ids, dtype=object)
        chunks = [
            ts.ravel().tolist(),
            rows,
            cols,
            np.repeat(ids, ts.shape[1]),
            [hashes[c] for c in content.tolist()],
            rng.integers(10, 200, size=n, dtype=np.int32),
        ]
        used: dict[bytes, int] = {}
        for c in np.unique(content).tolist():
            used.setdefault(hashes[c], c)  # one row per hash per day, as append writes
        the_day = date.fromordinal(date(1970, 1, 1).toordinal() + day)
        contents = [
            list(used),
            [the_day] * len(used),
            [self.meta.chunk_width] * len(used),
            [self.meta.chunk_height] * len(used),
            [self._zlib[c] for c in used.values()],
        ]
        return chunks, contents
