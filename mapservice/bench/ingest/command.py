"""`mapservice bench ingest`: a series of runs (or a ceiling search), their table and JSON."""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any

from mapservice.bench.ingest.report import (
    BASELINE_2019,
    MIN_JUDGED_S,
    POLL_P99_MAX_S,
    PUSH_P99_MAX_S,
    SCHEDULE_MIN_PERCENT,
    SMALL_FLEET,
    SMALL_FLEET_P99_S,
    SUSTAINED_MIN_FRACTION,
    TARGETS,
    _json_safe,
    _mb,
    _s,
    judged,
    latency_clients,
    live_bounds,
    loss_side,
    medians,
    print_results,
)
from mapservice.bench.ingest.run import run_once
from mapservice.bench.machine import machine_facts
from mapservice.bench.workdir import bench_data_dir


def run_series(args, base: Path, console) -> tuple[list[dict], dict]:
    """`--repeat` runs of `args.robots` robots (fresh stack each, under `base`); their medians."""
    runs: list[dict] = []
    for i in range(1, args.repeat + 1):
        run_dir = base / f"run-{i}"
        if run_dir.exists():
            shutil.rmtree(run_dir)
        result = run_once(args, run_dir, i, args.repeat, console)
        runs.append(result)
        cpu = result["cpu_percent_of_one_core"]
        console.print(
            f"run {i} ({args.robots:,} robots): lost {result['lost']}, duplicated "
            f"{result['duplicated']}, generator {result['loadgen_schedule_percent'] or 0:.2f} % "
            f"of schedule, p99 stored {_s(result['stored_latency_p99_s'])} (server) / push "
            f"{_s(result.get('latency_pushed_p99_s'))} / poll "
            f"{_s(result.get('latency_polled_p99_s'))}, sustained "
            f"{result['sustained_events_per_s']:,.0f}/s, "
            f"{_mb(result['bytes_per_robot_day'])}/robot-day, CPU {cpu['stack_total']:.0f} % "
            f"stack + {cpu['loadgen']:.0f} % loadgen, load {result['loadavg_1min_after_fleet']:.2f}"
        )
        if result["lost"]:
            console.print(f"[red]{loss_side(result['gateway_acked_minus_published'])}[/red]")
    return runs, medians(runs)


def ceiling_verdict(steps: list[dict]) -> int | None:
    """The largest fleet of consecutive steps from the first that held every bound."""
    largest = None
    for step in steps:
        if not step["held"]:
            break
        largest = step["robots"]
    return largest


def find_ceiling(args, facts: dict, base: Path, console) -> dict:
    """Steps the fleet up until a step's medians miss a bound (or --ceiling-max)."""
    import argparse

    steps: list[dict] = []
    robots = args.robots
    while robots <= args.ceiling_max:
        step_args = argparse.Namespace(**{**vars(args), "robots": robots})
        runs, med = run_series(step_args, base / f"robots-{robots}", console)
        print_results(console, step_args, facts, runs, med)
        checks = live_bounds(robots, med, latency_clients(args))
        held = all(ok for *_, ok in checks)
        steps.append(
            {
                "robots": robots,
                "held": held,
                "missed": [name for name, _, _, ok in checks if not ok],
                "medians": med,
                "runs": runs,
            }
        )
        console.print(
            f"{robots:,} robots: "
            + ("held every bound" if held else "missed " + ", ".join(steps[-1]["missed"]))
        )
        if not held:
            break
        robots += args.ceiling_step
    largest = ceiling_verdict(steps)
    console.print(
        f"[bold]largest fleet that held every bound: "
        f"{f'{largest:,} robots' if largest else 'none of the steps'}[/bold]"
        + ("" if judged(args.seconds) else f" (runs of {args.seconds:.0f} s: not representative)")
    )
    return {"steps": steps, "largest_fleet_held": largest}


def main(args) -> None:
    with bench_data_dir(args.data_dir, "mapservice-bench-") as base:
        _main(args, base)


def _main(args, base: Path) -> None:
    from rich.console import Console

    from mapservice.runtime.logs import configure

    configure("WARNING", "console", "bench")
    console = Console()
    if not console.is_terminal:
        console = Console(width=120)  # a log file: keep the result table on one line a row
    if args.robots < 1 or args.seconds <= 0 or args.repeat < 1:
        sys.exit("--robots, --seconds and --repeat must be positive")
    facts = machine_facts()
    doc: dict[str, Any] = {
        "benchmark": "ingest",
        "command": "mapservice bench ingest "
        + " ".join(sys.argv[3:] if sys.argv[1:3] == ["bench", "ingest"] else sys.argv[1:]),
        "args": {
            "robots": args.robots,
            "seconds": args.seconds,
            "mqtt": args.mqtt,
            "repeat": args.repeat,
            "data_dir": str(base),
            "loadgen": getattr(args, "loadgen", "raw"),
        },
        "machine": facts,
        "targets": TARGETS,
        "live_bounds": {
            "schedule_min_percent": SCHEDULE_MIN_PERCENT,
            "sustained_min_fraction": SUSTAINED_MIN_FRACTION,
            "push_p99_max_s": PUSH_P99_MAX_S,
            "poll_p99_max_s": POLL_P99_MAX_S,
            "small_fleet": SMALL_FLEET,
            "small_fleet_p99_s": SMALL_FLEET_P99_S,
            "min_judged_s": MIN_JUDGED_S,
        },
        "baseline_2019": BASELINE_2019,
    }
    if getattr(args, "find_ceiling", False):
        doc["ceiling"] = find_ceiling(args, facts, base, console)
    else:
        runs, med = run_series(args, base, console)
        print_results(console, args, facts, runs, med)
        doc.update(
            {
                "medians": med,
                "runs": runs,
                "bounds_held": all(
                    ok for *_, ok in live_bounds(args.robots, med, latency_clients(args))
                )
                if judged(args.seconds)
                else None,
            }
        )
    doc["machine"]["loadavg_at_end"] = os.getloadavg()
    if args.json:
        Path(args.json).write_text(json.dumps(_json_safe(doc), indent=2, default=str))
        console.print(f"results written to {args.json}")
