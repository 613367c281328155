"""`mapservice load-history`: days of realistic history, written fast into the history tables.

The workload is the 2019 load test's (and `loadgen.py`'s): every robot reports one pose a
second while driving a 1 m circle, and every fifth pose it sends one chunk: a real chunk
of the map re-sent at a random (row, column) of the grid. A small share of the chunk
writes carry changed pixels (a painted rectangle), so `chunk_contents` holds more than the
map's own chunks.

Nothing goes through envelopes, Kafka or `ClickHouseStore.append`: the rows are generated
as numpy columns, one UTC day at a time (one part per day partition, bounded memory), and
inserted column-oriented into the same tables `append` writes (`chunk_contents` first,
then `chunk_events`, then `poses` and `pose_derivations`, which feeds the pose views),
with the values `append` would store for the same events. The snapshots are then built by `ClickHouseStore.build_snapshots_bulk`, which
produces the rows `build_snapshots` would.

Every circle lies on free pixels: a robot's centre is a free cell of
`mapfile.free_cells_metres` whose whole 1 m ring (every pixel the circle can touch, after
rounding to millimetres) is free, so every stored pose is on a free cell of the map.
"""

from __future__ import annotations

import math
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, date, datetime
from pathlib import Path

import numpy as np

from mapservice.adapters.clickhouse.writes import POSE_INSERT_COLUMNS
from mapservice.adapters.ros_map import RosMap, free_cells_metres, meta_for, slice_chunks
from mapservice.core.events import MapMetaSet, make_envelope
from mapservice.core.wire2019 import content_hash

DAY_MS = 86_400_000
POSE_PERIOD_MS = 1000
CHUNK_EVERY = 5  # poses per chunk, as in the 2019 load test
RADIUS_M = 1.0  # the circle each robot drives (loadgen.py)
ANGULAR_SPEED = 0.2  # rad/s (loadgen.py)
# A retention guard: rows within this much of the retention edge would be dropped by the
# processors' retention step while a benchmark still reads them, so the loader never
# writes them.
TTL_GUARD_MS = 3_600_000
LOADER_ROBOT = "history-loader"

CHUNK_COLUMNS = ["ts", "row", "col", "robot_id", "content_hash", "recv_lag_ms"]
CONTENT_COLUMNS = ["content_hash", "day", "width", "height", "zlib_pixels"]


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


@dataclass
class LoadResult:
    start_ms: int
    end_ms: int  # every event time is in [start_ms, end_ms)
    robots: int
    poses: int = 0
    chunk_events: int = 0
    chunk_contents: int = 0  # rows written (one per content hash per day)
    distinct_contents: int = 0
    snapshots: int = 0
    generate_s: float = 0.0
    insert_s: float = 0.0
    snapshot_s: float = 0.0
    meta: MapMetaSet | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def load_s(self) -> float:
        return self.generate_s + self.insert_s


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
        self.base_contents = len(self._hashes)

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


def parse_end(text: str | None) -> int:
    """`now`, epoch milliseconds or an ISO time (UTC unless it says otherwise) -> epoch ms."""
    if text is None or text == "now":
        return time.time_ns() // 1_000_000
    if text.isdigit():
        return int(text)
    dt = datetime.fromisoformat(text)
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return int(dt.timestamp() * 1000)


def plan_window(
    days: float, end_ms: int, retention_days: int, now_ms: int | None = None
) -> tuple[int, int, list[str]]:
    """[start, end) of whole seconds, inside the retention (less the guard)."""
    now_ms = time.time_ns() // 1_000_000 if now_ms is None else now_ms
    notes: list[str] = []
    if days <= 0:
        raise ValueError("--days must be positive")
    if end_ms > now_ms + 1000:
        raise ValueError("--end lies in the future; history ends at the latest now")
    end = end_ms // 1000 * 1000
    start = end - round(days * DAY_MS) // 1000 * 1000
    earliest = -(-(now_ms - retention_days * DAY_MS + TTL_GUARD_MS) // 1000) * 1000
    if start < earliest:
        notes.append(
            f"the window starts {(earliest - start) / 60_000:.0f} min later than asked: rows "
            f"older than {retention_days} days (less a {TTL_GUARD_MS // 60_000} min guard) "
            "would be dropped by the retention step"
        )
        start = earliest
    if start >= end:
        raise ValueError(
            f"nothing to load: the window lies outside the {retention_days}-day retention"
        )
    return start, end, notes


def load_history(
    store,
    ros_map: RosMap,
    *,
    days: float,
    robots: int,
    end_ms: int | None = None,
    grid: tuple[int, int] | None = None,
    seed: int = 7,
    change_prob: float = 0.01,
    snapshots: bool = True,
    bulk_snapshots: bool = True,
    allow_existing: bool = False,
    on_progress: Callable[[str, int, int, dict], None] | None = None,
) -> LoadResult:
    """Writes `days` of history for `robots` robots ending at `end_ms` into `store`.

    `store` is a ClickHouseStore (migrated here). `on_progress(phase, done, total, info)`
    is called after each day ("load", seconds of history) and each snapshot batch
    ("snapshots"). Refuses a database that already holds poses or chunk events unless
    `allow_existing` (late history under existing snapshots would need a rebuild).
    """
    store.migrate()
    db = store.database
    client = store.client
    if not allow_existing:
        (n,) = client.query(
            f"SELECT (SELECT count() FROM {db}.poses) + (SELECT count() FROM {db}.chunk_events)"
        ).result_rows[0]
        if n:
            raise ValueError(
                f"database {db!r} already holds {n} rows of history; load into "
                "an empty one (another --data-dir or --database)"
            )
    end_ms = parse_end(None) if end_ms is None else end_ms
    start, end, notes = plan_window(days, end_ms, store.retention_days)
    rows, cols = grid if grid is not None else (None, None)
    meta = grid_meta(
        ros_map, rows, cols, comment=f"history-loader: {robots} robots, {days:g} days, seed {seed}"
    )
    gen = HistoryGenerator(
        ros_map, robots, start, end, meta=meta, seed=seed, change_prob=change_prob
    )
    result = LoadResult(start_ms=start, end_ms=gen.end_ms, robots=robots, meta=meta, notes=notes)
    # The grid in force for the whole window (the API validates chunk cells against it).
    store.append([make_envelope(LOADER_ROBOT, start, start, meta)])
    done = 0
    for k_lo, k_hi in gen.days():
        t0 = time.perf_counter()
        block = gen.block(k_lo, k_hi)
        t1 = time.perf_counter()
        with store._lock:
            client.insert(
                f"{db}.chunk_contents",
                data=block.contents,
                column_names=CONTENT_COLUMNS,
                column_oriented=True,
            )
            client.insert(
                f"{db}.chunk_events",
                data=block.chunks,
                column_names=CHUNK_COLUMNS,
                column_oriented=True,
            )
            client.insert(
                f"{db}.poses",
                data=block.poses,
                column_names=POSE_INSERT_COLUMNS,
                column_oriented=True,
            )
            # The pose views read the Null table pose_derivations (schema v10), as
            # `derive_views` feeds them.
            client.insert(
                f"{db}.pose_derivations",
                data=block.poses,
                column_names=POSE_INSERT_COLUMNS,
                column_oriented=True,
            )
        t2 = time.perf_counter()
        result.generate_s += t1 - t0
        result.insert_s += t2 - t1
        result.poses += block.n_poses
        result.chunk_events += block.n_chunks
        result.chunk_contents += len(block.contents[0])
        done += k_hi - k_lo
        del block
        if on_progress is not None:
            on_progress(
                "load", done, gen.seconds, {"poses": result.poses, "chunks": result.chunk_events}
            )
    result.distinct_contents = gen.distinct_contents
    if snapshots:
        t0 = time.perf_counter()
        if bulk_snapshots:
            result.snapshots = store.build_snapshots_bulk(
                gen.end_ms,
                on_progress=None
                if on_progress is None
                else (lambda d, t: on_progress("snapshots", d, t, {})),
            )
        else:
            result.snapshots = store.build_snapshots(gen.end_ms)
        result.snapshot_s = time.perf_counter() - t0
    return result


def main(args) -> None:
    """The `mapservice load-history` command."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.robot import DEFAULT_MAP
    from mapservice.settings import Settings

    console = Console()
    settings = Settings(
        data_dir=Path(args.data_dir),
        **({"clickhouse_dsn": args.clickhouse_dsn} if args.clickhouse_dsn else {}),
    )
    grid = None
    if args.grid:
        r, _, c = args.grid.lower().partition("x")
        grid = (int(r), int(c))
    store = ClickHouseStore(
        settings.resolved_clickhouse_dsn,
        args.database or settings.clickhouse_database,
        settings.retention_days,
        settings.clickhouse_username,
        settings.clickhouse_password.get_secret_value(),
        int((args.snapshot_every_s or settings.snapshot_every_s) * 1000),
    )
    ros_map = load_ros_map(args.map or DEFAULT_MAP)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    try:
        with Progress(*columns, console=console) as progress:
            tasks: dict[str, int] = {}

            def on_progress(phase: str, done: int, total: int, info: dict) -> None:
                if phase not in tasks:
                    label = "history (s)" if phase == "load" else "snapshots"
                    tasks[phase] = progress.add_task(label, total=total, info="")
                text = ", ".join(f"{v:,} {k}" for k, v in info.items())
                progress.update(tasks[phase], completed=done, total=total, info=text)

            result = load_history(
                store,
                ros_map,
                days=args.days,
                robots=args.robots,
                end_ms=parse_end(args.end),
                grid=grid,
                seed=args.seed,
                change_prob=args.change_prob,
                snapshots=not args.no_snapshots,
                on_progress=on_progress,
            )
            if args.optimize:
                t0 = time.perf_counter()
                progress.console.print("merging parts (OPTIMIZE FINAL)...")
                store.optimize()
                progress.console.print(f"merged in {time.perf_counter() - t0:.1f} s")
    except ValueError as exc:
        raise SystemExit(f"load-history: {exc}") from None
    finally:
        store.close()

    def fmt(ms):
        return datetime.fromtimestamp(ms / 1000, UTC).strftime("%Y-%m-%d %H:%M:%S")

    for note in result.notes:
        console.print(f"[yellow]note:[/yellow] {note}")
    console.print(
        f"loaded {result.poses:,} poses, {result.chunk_events:,} chunk events and "
        f"{result.chunk_contents:,} chunk content rows ({result.distinct_contents:,} distinct) "
        f"for {result.robots} robots, {fmt(result.start_ms)} to {fmt(result.end_ms)} UTC, "
        f"on a {result.meta.chunk_rows} x {result.meta.chunk_cols} chunk grid, in "
        f"{result.load_s:.1f} s (generate {result.generate_s:.1f} s, insert "
        f"{result.insert_s:.1f} s); {result.snapshots} snapshots in {result.snapshot_s:.1f} s"
    )
    console.print(
        f"into {settings.resolved_clickhouse_dsn} database "
        f"{args.database or settings.clickhouse_database}"
    )


def add_parser(sub) -> None:
    p = sub.add_parser(
        "load-history",
        help="write days of simulated 2019-workload history straight into ClickHouse",
    )
    p.add_argument(
        "--days", type=float, default=1.0, help="days of history (at most the retention)"
    )
    p.add_argument("--robots", type=int, default=20, help="simulated robots")
    p.add_argument("--map", default=None, help="ROS map YAML (default: maps/warehouse.yaml)")
    p.add_argument(
        "--data-dir",
        default=".mapservice-data",
        help="embedded chDB under DIR/clickhouse (as `mapservice up`)",
    )
    p.add_argument("--clickhouse-dsn", default=None, help="a ClickHouse server or chdb:// instead")
    p.add_argument("--database", default=None, help="default: MAPSERVICE_CLICKHOUSE_DATABASE")
    p.add_argument(
        "--end", default="now", help="`now`, epoch ms or ISO time (UTC) of the last event"
    )
    p.add_argument(
        "--grid",
        default=None,
        help="ROWSxCOLS chunk grid (e.g. 32x48); default: the map's own chunks",
    )
    p.add_argument("--seed", type=int, default=7, help="random seed (same seed, same history)")
    p.add_argument(
        "--change-prob", type=float, default=0.01, help="share of chunk writes with changed pixels"
    )
    p.add_argument(
        "--snapshot-every-s",
        type=float,
        default=None,
        help="default: MAPSERVICE_SNAPSHOT_EVERY_S (600)",
    )
    p.add_argument("--no-snapshots", action="store_true", help="skip building the snapshots")
    p.add_argument(
        "--optimize", action="store_true", help="merge parts (OPTIMIZE FINAL) at the end"
    )
    p.set_defaults(func=main)
