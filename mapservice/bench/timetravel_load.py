"""`mapservice bench timetravel`'s history: loaded with the history loader (the first
snapshots built one by one to time the service's path, the rest in bulk, the parts merged),
or reused from an earlier run's data directory, with what the load took.
"""

from __future__ import annotations

import json
import time
from datetime import UTC, datetime
from pathlib import Path

from mapservice.bench.timetravel_measure import busy_processes

LOAD_FILE = "history-load.json"


def load(store, args, data_dir: Path, console, busy_at_start: list[str]) -> dict:
    """Loads the history (or reuses it) and returns what the load took."""
    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.bench.history_loader import load_history
    from mapservice.bench.load_history_cli import load_progress
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
    with load_progress(console, "snapshots (bulk)") as (_, on_progress):
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
