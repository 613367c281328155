"""`mapservice bench ingest --kafka both`: one workload on the embedded Apache Kafka and on
tansu in one run, side by side.

Each of `--repeat` rounds runs the ingest benchmark (bench/ingest/run.py's `run_once`: a fresh
stack, the robots, the drain) once on each broker, alternating which goes first, so both
see the same machine: this machine is shared, and what another user runs meanwhile moves
both brokers' figures. The ratio between the brokers in one run is what to read; the load
average around every run is recorded beside it.

Per broker (medians over the rounds): CPU per published event of each component, the
broker's included; publish-to-queryable latency p50/p99; resident memory of each component
when the robots stop; events lost and duplicated.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from argparse import Namespace
from pathlib import Path

from mapservice.bench.workdir import bench_data_dir

BROKERS = ("apache", "tansu")
COMPONENTS = ("kafka", "gateway", "server", "mqtt")
BROKER_NAMES = {"apache": "Apache Kafka", "tansu": "tansu"}


def run_rounds(args, base: Path, console, run_once) -> dict[str, list[dict]]:
    """`args.repeat` rounds, each a run per broker (the first broker alternating)."""
    runs: dict[str, list[dict]] = {b: [] for b in BROKERS}
    for i in range(1, args.repeat + 1):
        order = BROKERS if i % 2 else tuple(reversed(BROKERS))
        for broker in order:
            run_dir = base / broker / f"run-{i}"
            shutil.rmtree(run_dir, ignore_errors=True)
            before = os.getloadavg()
            result = run_once(
                Namespace(**{**vars(args), "kafka": broker}), run_dir, i, args.repeat, console
            )
            result["broker"] = broker
            result["loadavg_before_run"] = before
            runs[broker].append(result)
            console.print(
                f"round {i} on {BROKER_NAMES[broker]}: lost {result['lost']}, duplicated "
                f"{result['duplicated']}, p99 {_s(result.get('latency_p99_s'))}, "
                f"load {result['loadavg_1min_after_fleet']:.2f}"
            )
    return runs


def side_by_side(med: dict[str, dict[str, float]]) -> list[tuple[str, dict[str, float | None]]]:
    """The compared measures, each with its median per broker (None: not measured)."""
    rows: list[tuple[str, str]] = [
        (f"CPU per event: {c} (µs)", f"cpu_us_per_event.{c}") for c in COMPONENTS
    ]
    rows += [
        ("CPU per event: stack total (µs)", "cpu_us_per_event.stack_total"),
        ("latency publish -> queryable p50 (s)", "latency_p50_s"),
        ("latency publish -> queryable p99 (s)", "latency_p99_s"),
    ]
    rows += [(f"memory: {c} (MB resident)", f"rss_mb_after_fleet.{c}") for c in COMPONENTS]
    rows += [
        ("sustained (events/s)", "sustained_events_per_s"),
        ("lost", "lost"),
        ("duplicated", "duplicated"),
        ("load average (1 min) after the fleet", "loadavg_1min_after_fleet"),
    ]
    return [(label, {b: med.get(b, {}).get(key) for b in BROKERS}) for label, key in rows]


def ratio(values: dict[str, float | None]) -> float | None:
    """Apache Kafka's figure over tansu's (None where either is missing or tansu's is 0)."""
    a, t = values.get("apache"), values.get("tansu")
    if a is None or t is None or t == 0:
        return None
    return a / t


def _s(v) -> str:
    return "n/a" if v is None else f"{v:.3f} s"


def _fmt(v: float | None) -> str:
    if v is None:
        return "n/a"
    return f"{v:,.0f}" if abs(v) >= 100 else f"{v:,.3g}"


def print_table(console, args, rows) -> None:
    from rich.table import Table

    table = Table(
        title=f"mapservice bench ingest --kafka both: {args.robots:,} robots, "
        f"{args.seconds:.0f} s, MQTT {args.mqtt}, median of {args.repeat} "
        f"round(s)"
    )
    table.add_column("measure")
    for broker in BROKERS:
        table.add_column(BROKER_NAMES[broker], justify="right")
    table.add_column("Apache / tansu", justify="right")
    for label, values in rows:
        r = ratio(values)
        table.add_row(
            label, *(_fmt(values[b]) for b in BROKERS), "n/a" if r is None else f"{r:.2f}x"
        )
    console.print(table)


def main(args) -> None:
    from rich.console import Console

    from mapservice.bench.ingest.report import _json_safe, medians
    from mapservice.bench.ingest.run import run_once
    from mapservice.bench.machine import machine_facts
    from mapservice.runtime.logs import configure

    configure("WARNING", "console", "bench")
    console = Console()
    if not console.is_terminal:
        console = Console(width=120)
    if args.robots < 1 or args.seconds <= 0 or args.repeat < 1:
        sys.exit("--robots, --seconds and --repeat must be positive")
    if getattr(args, "find_ceiling", False):
        sys.exit("--kafka both compares the brokers at one fleet size: drop --find-ceiling")
    facts = machine_facts()
    with bench_data_dir(args.data_dir, "mapservice-brokers-") as base:
        runs = run_rounds(args, base, console, run_once)
    med = {broker: medians(r) for broker, r in runs.items()}
    rows = side_by_side(med)
    print_table(console, args, rows)
    facts["loadavg_at_end"] = os.getloadavg()
    doc = {
        "benchmark": "ingest --kafka both",
        "command": "mapservice " + " ".join(sys.argv[1:]),
        "args": {
            "robots": args.robots,
            "seconds": args.seconds,
            "mqtt": args.mqtt,
            "repeat": args.repeat,
            "data_dir": str(base),
        },
        "machine": facts,
        "side_by_side": [
            {"measure": label, **values, "apache_over_tansu": ratio(values)}
            for label, values in rows
        ],
        "medians": med,
        "runs": runs,
    }
    if args.json:
        Path(args.json).write_text(json.dumps(_json_safe(doc), indent=2, default=str))
        console.print(f"results written to {args.json}")
