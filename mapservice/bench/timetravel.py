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

The load is in timetravel_load.py, the timed reads in timetravel_measure.py (their naive
counterparts in timetravel_naive.py), the markdown section in timetravel_report.py.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from datetime import UTC, datetime
from pathlib import Path

from mapservice.bench.timetravel_load import load
from mapservice.bench.timetravel_measure import busy_processes, measure, wait_quiet
from mapservice.bench.timetravel_report import HEADER, markdown, table_rows
from mapservice.bench.workdir import DATA_DIR_HELP, bench_data_dir


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


def main(args) -> None:
    with bench_data_dir(args.data_dir, "tt-bench-") as data_dir:
        _main(args, data_dir)


def _main(args, data_dir: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    from mapservice.adapters.clickhouse.store import ClickHouseStore

    console = Console()
    if not console.is_terminal:
        console = Console(width=150)
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
    tt.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
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
