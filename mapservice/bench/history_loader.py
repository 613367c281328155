"""`mapservice load-history`: days of realistic history, written fast into the history tables.

The workload is the 2019 load test's (and `loadgen.py`'s), generated as numpy columns by
`history_generator.py`: every robot a pose a second driving a 1 m circle, every fifth pose
a chunk of the map re-sent at a random cell of the grid, a small share with changed pixels.

Nothing goes through envelopes, Kafka or `ClickHouseStore.append`: the rows are generated
one UTC day at a time (one part per day partition, bounded memory), and inserted
column-oriented into the same tables `append` writes (`chunk_contents` first, then
`chunk_events`, then `poses` and `pose_derivations`, which feeds the pose views), with the
values `append` would store for the same events. The snapshots are then built by
`ClickHouseStore.build_snapshots_bulk`, which produces the rows `build_snapshots` would.
The command's flags and progress display are in `load_history_cli.py`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime

from mapservice.adapters.clickhouse.writes import POSE_INSERT_COLUMNS
from mapservice.adapters.ros_map import RosMap
from mapservice.bench.history_generator import DAY_MS, HistoryGenerator, grid_meta
from mapservice.core.events import MapMetaSet, make_envelope

# A retention guard: rows within this much of the retention edge would be dropped by the
# processors' retention step while a benchmark still reads them, so the loader never
# writes them.
TTL_GUARD_MS = 3_600_000
LOADER_ROBOT = "history-loader"

CHUNK_COLUMNS = ["ts", "row", "col", "robot_id", "content_hash", "recv_lag_ms"]
CONTENT_COLUMNS = ["content_hash", "day", "width", "height", "zlib_pixels"]


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
        with store.lock:
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
