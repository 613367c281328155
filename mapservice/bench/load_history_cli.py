"""The `mapservice load-history` command: its flags, a progress display and the summary."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from mapservice.bench.history_loader import load_history, parse_end

if TYPE_CHECKING:
    from rich.progress import Progress


@contextmanager
def load_progress(
    console, snapshots_label: str = "snapshots"
) -> Iterator[tuple[Progress, Callable[[str, int, int, dict], None]]]:
    """Rich progress bars for the history loader (also `bench timetravel`'s): the bars and
    the `on_progress` that feeds them, a bar per phase (history seconds, snapshot batches)."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TaskID,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console) as progress:
        tasks: dict[str, TaskID] = {}

        def on_progress(phase: str, done: int, total: int, info: dict) -> None:
            if phase not in tasks:
                label = "history (s)" if phase == "load" else snapshots_label
                tasks[phase] = progress.add_task(label, total=total, info="")
            text = ", ".join(f"{v:,} {k}" for k, v in info.items())
            progress.update(tasks[phase], completed=done, total=total, info=text)

        yield progress, on_progress


def main(args) -> None:
    """The `mapservice load-history` command."""
    from rich.console import Console

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
    try:
        with load_progress(console) as (progress, on_progress):
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
