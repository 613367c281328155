"""`mapservice bench timetravel`: reads of a week of history, measured side by side.

One run:

1. load `--days` of the 2019 workload for `--robots` robots with the history loader
   (`history_loader.py`), ending now, on a `--grid` chunk grid (default 32 x 48 = 1,536
   chunks of 100 x 100 pixels: warehouse.yaml has only 17 x 11 = 187 chunks, so its chunks
   are re-sent at random cells of the larger grid, as the 2019 load test re-sent them);
   build the first snapshots one by one (`build_snapshots`, to time it), the rest with
   `build_snapshots_bulk`, then merge the parts (OPTIMIZE FINAL), as a long-running
   service's background merges would have;
2. warm up, then for `--queries` random instants T (and as many in the last hour and
   around six days ago) time, interleaved so noise hits every query alike:
   - `map_at(T)` (nearest snapshot + events after it) and the naive query (latest write
     per chunk over the whole history up to T), and check they are equal;
   - `robots_at(T)` and its naive query (latest pose per robot over all poses <= T),
     checked equal too;
   - a 10 s event window: `chunk_events` + `poses` over [T, T + 10 s) (what
     GET /api/v1/events reads);
   - a one-day window of poses downsampled to one pose per robot per `--step-s` (default
     60 s: 1,440 frames a day, finer than replays need) and per 8,640 s (86400x at 10
     frames/s), the window starting on a whole minute (the keyframe path, schema v4), side
     by side with the same answer computed from every pose (the pre-v4 query), checked
     equal; and the 86400x step from a start off the minute (keyframes plus the first
     minute of each step from `poses`), checked equal every fourth round;
   - the timeline over the whole history in 10-minute buckets and over one day in 1,000
     buckets of 86.4 s (GET /api/v1/timeline), side by side with the same buckets counted
     from every event (the pre-v9 query: chunk_events FINAL, every pose), checked equal;
     and a robot's track over a day at the step (GET /api/v1/robots/{id}/track).

Latencies are wall time around the store call, in this process (embedded chDB), from the
call to the Python rows: what an API handler would wait. p99 is numpy's linear
percentile over the samples.
"""

from __future__ import annotations

import json
import os
import platform
import random
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from mapservice.bench.timetravel_naive import (
    naive_map_at,
    naive_poses_downsampled,
    naive_robots_at,
    naive_timeline,
)
from mapservice.bench.timetravel_report import HEADER, markdown, table_rows

DAY_MS = 86_400_000
HOUR_MS = 3_600_000
BUSY_PATTERNS = ("bench ingest", "exp.py", "tansu", "kafka.Kafka", "mosquitto")
LOAD_FILE = "history-load.json"


# --- machine facts --------------------------------------------------------------------------


def machine_facts() -> dict:
    from mapservice.bench.machine import cpu_model

    model = cpu_model()
    import clickhouse_connect

    try:
        import chdb

        chdb_version = chdb.__version__
    except ImportError:  # a server DSN needs no chdb
        chdb_version = "-"
    import psutil

    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "ram_gib": round(psutil.virtual_memory().total / 2**30, 1),
        "python": platform.python_version(),
        "chdb": chdb_version,
        "clickhouse_connect": clickhouse_connect.__version__,
    }


def busy_processes() -> list[str]:
    """Other benchmarks running on this machine (they would skew the latencies)."""
    import psutil

    me = os.getpid()
    found = []
    for p in psutil.process_iter(["pid", "name", "cmdline"]):
        try:
            if p.info["pid"] == me:
                continue
            cmd = " ".join(p.info["cmdline"] or []) or (p.info["name"] or "")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        if any(pat in cmd for pat in BUSY_PATTERNS):
            found.append(f"{p.info['pid']} {cmd[:80]}")
    return found


# --- measuring ------------------------------------------------------------------------------


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return (time.perf_counter() - t0) * 1000, out


def summary(samples: list[float]) -> dict:
    a = np.asarray(samples, dtype=float)
    if a.size == 0:
        return {"n": 0}
    return {
        "n": int(a.size),
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
        "mean": float(a.mean()),
    }


def load(store, args, data_dir: Path, console, busy_at_start: list[str]) -> dict:
    """Loads the history (or reuses it) and returns what the load took."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.bench.history_loader import load_history
    from mapservice.robot import DEFAULT_MAP

    store.migrate()
    db = store.database
    (rows,) = store.client.query(f"SELECT count() FROM {db}.poses").result_rows[0]
    info_path = data_dir / LOAD_FILE
    if rows:
        if not args.reuse:
            raise SystemExit(
                f"{data_dir} already holds history: pass --reuse to measure it "
                "again, or an empty --data-dir to load afresh"
            )
        info = json.loads(info_path.read_text()) if info_path.exists() else {}
        info["reused"] = True
        return info
    grid = tuple(int(v) for v in args.grid.lower().split("x"))
    ros_map = load_ros_map(args.map or DEFAULT_MAP)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console) as progress:
        tasks: dict[str, int] = {}

        def on_progress(phase: str, done: int, total: int, info: dict) -> None:
            if phase not in tasks:
                tasks[phase] = progress.add_task(
                    "history (s)" if phase == "load" else "snapshots (bulk)", total=total, info=""
                )
            progress.update(
                tasks[phase],
                completed=done,
                total=total,
                info=", ".join(f"{v:,} {k}" for k, v in info.items()),
            )

        result = load_history(
            store,
            ros_map,
            days=args.days,
            robots=args.robots,
            grid=grid,
            seed=args.seed,
            snapshots=False,
            on_progress=on_progress,
        )
        # The first snapshots one by one (the service's path), to know what it costs...
        every = store.snapshot_every_ms
        first = result.start_ms // every * every
        t0 = time.perf_counter()
        one_by_one = store.build_snapshots(first + (args.one_by_one - 1) * every)
        one_by_one_s = time.perf_counter() - t0
        # ...and the rest in bulk, continuing from them.
        t0 = time.perf_counter()
        bulk = store.build_snapshots_bulk(
            result.end_ms, on_progress=lambda d, t: on_progress("snapshots", d, t, {})
        )
        bulk_s = time.perf_counter() - t0
    with console.status("merging parts (OPTIMIZE FINAL)..."):
        t0 = time.perf_counter()
        store.optimize()
        optimize_s = time.perf_counter() - t0
    info = {
        "reused": False,
        "days": args.days,
        "robots": args.robots,
        "grid": list(grid),
        "chunks": grid[0] * grid[1],
        "start_ms": result.start_ms,
        "end_ms": result.end_ms,
        "poses": result.poses,
        "chunk_events": result.chunk_events,
        "chunk_content_rows": result.chunk_contents,
        "distinct_contents": result.distinct_contents,
        "generate_s": result.generate_s,
        "insert_s": result.insert_s,
        "load_s": result.load_s,
        "snapshots_one_by_one": one_by_one,
        "one_by_one_s": one_by_one_s,
        "snapshots_bulk": bulk,
        "bulk_s": bulk_s,
        "optimize_s": optimize_s,
        "notes": result.notes,
        "loaded_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "busy_during_load": sorted(set(busy_at_start) | set(busy_processes())),
    }
    info_path.write_text(json.dumps(info, indent=2))
    return info


def measure(store, args, start_ms: int, end_ms: int, console) -> dict:
    rng = random.Random(args.seed)
    n = args.queries
    every = store.snapshot_every_ms
    step_ms = int(args.step_s * 1000)
    replay_step_ms = DAY_MS // 10  # 86400x at 10 frames/s: a frame per 8,640 s
    span = end_ms - start_ms
    old_centre = end_ms - 6 * DAY_MS if span > 6 * DAY_MS + HOUR_MS else start_ms + span // 2
    sets = {
        "random": [rng.randint(start_ms + every, end_ms) for _ in range(n)],
        "last_hour": [rng.randint(end_ms - HOUR_MS, end_ms) for _ in range(max(1, n // 2))],
        "6_days_ago": [
            rng.randint(old_centre - HOUR_MS // 2, old_centre + HOUR_MS // 2)
            for _ in range(max(1, n // 2))
        ],
    }
    day_lo = start_ms + DAY_MS if span > DAY_MS + HOUR_MS else end_ms - span // 2
    windows = [rng.randint(start_ms, end_ms - 10_000) for _ in range(n)]
    # Replay windows start on a whole minute (a client asking for the fast path does).
    days = [rng.randint(day_lo, end_ms) // 60_000 * 60_000 for _ in range(n)]
    robot_ids = [r.robot_id for r in store.robots_at(end_ms)]
    week_from = (end_ms - min(span, 7 * DAY_MS)) // 60_000 * 60_000 + 60_000
    week_buckets = (end_ms - week_from) // 600_000  # whole 10-minute buckets
    t: dict[str, list[float]] = {
        k: []
        for k in (
            "map_at:random",
            "naive_map:random",
            "map_at:last_hour",
            "naive_map:last_hour",
            "map_at:6_days_ago",
            "naive_map:6_days_ago",
            "robots_at",
            "naive_robots",
            "window_10s",
            "day_downsampled",
            "naive_downsampled",
            "day_replay_86400x",
            "naive_replay_86400x",
            "replay_86400x_any_from",
            "timeline_week",
            "timeline_day",
            "naive_timeline_week",
            "naive_timeline_day",
            "track_day",
        )
    }
    checks = {
        "map_at_compared": 0,
        "map_at_mismatches": 0,
        "robots_compared": 0,
        "robots_mismatches": 0,
        "window_rows": 0,
        "downsampled_rows_max": 0,
        "downsampled_compared": 0,
        "downsampled_mismatches": 0,
        "chunks_per_map_min": None,
        "week_buckets": week_buckets,
        "timeline_compared": 0,
        "timeline_mismatches": 0,
    }

    def window(at: int):
        return store.chunk_events(at, at + 10_000), store.poses(at, at + 10_000)

    # Warm-up: caches, lazily loaded marks and the first-query costs, not measured.
    for at in sets["random"][:5]:
        store.map_at(at), naive_map_at(store, at), store.robots_at(at), naive_robots_at(store, at)
        window(at)
        store.poses_downsampled(at - DAY_MS, at, step_ms)
        store.timeline(week_from, week_from + week_buckets * 600_000, week_buckets)

    from rich.progress import Progress

    total = sum(len(v) for v in sets.values())
    rounds = busy_rounds = 0
    busy_seen: set[str] = set()
    with Progress(console=console) as progress:
        task = progress.add_task("queries", total=total)
        for name, instants in sets.items():
            for i, at in enumerate(instants):
                if rounds % 10 == 0:  # outside the timings: is another benchmark running?
                    busy = busy_processes()
                    busy_seen.update(busy)
                busy_rounds += bool(busy)
                rounds += 1
                ms, got = timed(store.map_at, at)
                t[f"map_at:{name}"].append(ms)
                ms, want = timed(naive_map_at, store, at)
                t[f"naive_map:{name}"].append(ms)
                checks["map_at_compared"] += 1
                checks["map_at_mismatches"] += got != want
                low = checks["chunks_per_map_min"]
                checks["chunks_per_map_min"] = len(got) if low is None else min(low, len(got))
                if name == "random":
                    ms, robots = timed(store.robots_at, at)
                    t["robots_at"].append(ms)
                    ms, naive = timed(naive_robots_at, store, at)
                    t["naive_robots"].append(ms)
                    checks["robots_compared"] += 1
                    checks["robots_mismatches"] += [(p.robot_id, p.ts_ms) for p in robots] != naive
                    ms, (chunks, poses) = timed(window, windows[i])
                    t["window_10s"].append(ms)
                    checks["window_rows"] = max(checks["window_rows"], len(chunks) + len(poses))
                    f, to = days[i] - DAY_MS, days[i]
                    for key, naive_key, step in (
                        ("day_downsampled", "naive_downsampled", step_ms),
                        ("day_replay_86400x", "naive_replay_86400x", replay_step_ms),
                    ):
                        ms, frames = timed(store.poses_downsampled, f, to, step)
                        t[key].append(ms)
                        ms, want = timed(naive_poses_downsampled, store, f, to, step)
                        t[naive_key].append(ms)
                        checks["downsampled_compared"] += 1
                        checks["downsampled_mismatches"] += frames != want
                        checks["downsampled_rows_max"] = max(
                            checks["downsampled_rows_max"], len(frames)
                        )
                    # A replay position is any millisecond: the 86400x step from there.
                    off = f + 1 + (i * 7_919) % 59_999
                    ms, frames = timed(store.poses_downsampled, off, off + DAY_MS, replay_step_ms)
                    t["replay_86400x_any_from"].append(ms)
                    if i % 4 == 0:  # checked, untimed; timelines, tracks: a quarter as many
                        checks["downsampled_compared"] += 1
                        checks["downsampled_mismatches"] += frames != naive_poses_downsampled(
                            store, off, off + DAY_MS, replay_step_ms
                        )
                        for key, args in (
                            (
                                "timeline_week",
                                (week_from, week_from + week_buckets * 600_000, week_buckets),
                            ),
                            ("timeline_day", (f, to, 1000)),
                        ):
                            ms, got = timed(store.timeline, *args)
                            t[key].append(ms)
                            ms, want = timed(naive_timeline, store, *args)
                            t[f"naive_{key}"].append(ms)
                            checks["timeline_compared"] += 1
                            checks["timeline_mismatches"] += got != want
                        if robot_ids:
                            ms, _ = timed(
                                store.poses_downsampled,
                                f,
                                to,
                                step_ms,
                                robot_ids[i % len(robot_ids)],
                            )
                            t["track_day"].append(ms)
                progress.advance(task)
    return {
        "latency_ms": {k: summary(v) for k, v in t.items()},
        "checks": checks,
        "step_ms": step_ms,
        "replay_step_ms": replay_step_ms,
        "rounds": rounds,
        "busy_rounds": busy_rounds,
        "busy_seen": sorted(busy_seen),
    }


def wait_quiet(seconds: float, console) -> float:
    """Waits (polling every 30 s) until no other benchmark runs, at most `seconds`."""
    t0 = time.monotonic()
    while (busy := busy_processes()) and time.monotonic() - t0 < seconds:
        console.print(
            f"waiting for a quiet machine ({len(busy)} benchmark processes, e.g. {busy[0][:60]})"
        )
        time.sleep(min(30.0, max(0.0, seconds - (time.monotonic() - t0))))
    return time.monotonic() - t0


def main(args) -> None:
    from rich.console import Console
    from rich.table import Table

    from mapservice.adapters.clickhouse.store import ClickHouseStore

    console = Console()
    if not console.is_terminal:
        console = Console(width=150)
    data_dir = Path(args.data_dir) if args.data_dir else Path(tempfile.mkdtemp(prefix="tt-bench-"))
    data_dir.mkdir(parents=True, exist_ok=True)
    dsn = args.clickhouse_dsn or f"chdb://{(data_dir / 'clickhouse').resolve()}"
    store = ClickHouseStore(dsn, database=args.database, snapshot_every_ms=600_000)
    results: dict = {
        "command": "mapservice " + " ".join(sys.argv[1:])
        if args.command_line is None
        else args.command_line,
        "machine": machine_facts(),
        "data_dir": str(data_dir),
    }
    try:
        busy = busy_processes()
        if busy:
            console.print(f"[yellow]other benchmarks are running: {busy}[/yellow]")
        results["load"] = load(store, args, data_dir, console, busy)
        db = store.database
        start_ms, end_ms = store.client.query(
            f"SELECT toUnixTimestamp64Milli(min(ts)), toUnixTimestamp64Milli(max(ts)) + 1 "
            f"FROM {db}.poses"
        ).result_rows[0]
        if args.wait_quiet:
            results["waited_s"] = wait_quiet(args.wait_quiet, console)
        results["loadavg_before"] = os.getloadavg()[0]
        results["busy_before"] = busy_processes()
        results["measure"] = measure(store, args, start_ms, end_ms, console)
        results["busy_after"] = busy_processes()
        results["loadavg_after"] = os.getloadavg()[0]
        results["storage"] = store.storage_bytes()
    finally:
        store.close()
    results["finished"] = datetime.now(UTC).isoformat(timespec="seconds")

    table = Table(
        title=f"time travel: {results['load'].get('days')} days x "
        f"{results['load'].get('robots')} robots"
    )
    for h in HEADER:
        table.add_column(h, justify="left" if h == "query" else "right")
    for row in table_rows(results["measure"]):
        table.add_row(*row)
    console.print(table)
    checks = results["measure"]["checks"]
    console.print(
        f"map_at == naive: {checks['map_at_compared']} instants, "
        f"{checks['map_at_mismatches']} mismatches; robots_at == naive: "
        f"{checks['robots_compared']} instants, {checks['robots_mismatches']} mismatches; "
        f"downsampled == naive: {checks['downsampled_compared']} windows, "
        f"{checks['downsampled_mismatches']} mismatches; timeline == naive: "
        f"{checks['timeline_compared']}, {checks['timeline_mismatches']} mismatches"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    if args.benchmarks_md:
        path = Path(args.benchmarks_md)
        text = markdown(results)
        if not path.exists():
            text = "# Benchmarks\n" + text
        with path.open("a") as f:
            f.write(text)
        console.print(f"appended to {path}")


def add_parser(kinds) -> None:
    tt = kinds.add_parser(
        "timetravel", help="map/robots at T and replay windows over a week of history"
    )
    tt.add_argument("--days", type=float, default=7, help="days of history loaded")
    tt.add_argument("--robots", type=int, default=20, help="simulated robots in the history")
    tt.add_argument("--grid", default="32x48", help="ROWSxCOLS chunk grid of the map meta")
    tt.add_argument("--map", default=None, help="ROS map YAML (default: maps/warehouse.yaml)")
    tt.add_argument("--data-dir", default=None, help="default: a fresh temporary directory")
    tt.add_argument(
        "--clickhouse-dsn",
        default=None,
        help="a ClickHouse server or chdb:// instead of the data dir",
    )
    tt.add_argument("--database", default="mapservice", help="ClickHouse database")
    tt.add_argument("--reuse", action="store_true", help="measure history loaded by an earlier run")
    tt.add_argument(
        "--queries",
        type=int,
        default=200,
        help="random instants (plus half as many in the last hour and half as many six days ago)",
    )
    tt.add_argument(
        "--step-s",
        type=float,
        default=60.0,
        help="downsampling step of the one-day window (whole minutes take the keyframe path)",
    )
    tt.add_argument(
        "--one-by-one",
        type=int,
        default=12,
        help="snapshots built one by one (timed) before the bulk build",
    )
    tt.add_argument(
        "--seed", type=int, default=7, help="random seed of the history and the instants"
    )
    tt.add_argument(
        "--wait-quiet",
        type=float,
        default=0,
        help="before measuring, wait up to this many seconds for other benchmarks "
        "(bench ingest, tansu, mosquitto) to end",
    )
    tt.add_argument("--json", default=None, help="write the results as JSON to this file")
    tt.add_argument(
        "--benchmarks-md",
        default=None,
        help="append a section to this file (e.g. docs/benchmarks-journal.md; "
        "BENCHMARKS.md quotes the latest run)",
    )
    tt.set_defaults(func=main, command_line=None)
