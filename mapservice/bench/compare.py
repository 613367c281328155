"""`mapservice bench ingest --compare A --compare B` (and `--kafka both`): one workload on two
variants of the stack, interleaved in the same hour, side by side with B's figure over A's.

A variant is a name and what differs: settings for the stack's components (`KEY=VALUE`, as
environment variables), the embedded broker (`kafka=apache|tansu`), or the Python of another
checkout (`python=/path/to/checkout/.venv/bin/python`: the components run that checkout's
code, measured by this one's harness), e.g.

    --compare main=python=../main/.venv/bin/python --compare branch=python=.venv/bin/python
    --compare wait50=MAPSERVICE_KAFKA_FETCH_WAIT_MS=50 --compare wait500=MAPSERVICE_KAFKA_FETCH_WAIT_MS=500

Each of `--repeat` rounds runs the ingest benchmark (bench/ingest/run.py's `run_once`: a fresh
stack, the robots, the drain) once per variant, alternating which goes first (A B, B A, ...),
so both see the same machine: on these machines absolute figures move by 2x with the hour,
and what another user runs meanwhile moves both. The ratio is what to read; the machine's
yardstick and the load average around every run are recorded beside it.

Per variant (medians over the rounds): CPU per published event of each component, the
broker's included; publish-to-queryable latency p50/p99; resident memory of each component
when the robots stop; events lost and duplicated.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from argparse import Namespace
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapservice.bench.workdir import bench_data_dir

COMPONENTS = ("kafka", "gateway", "server", "mqtt")
_BROKERS = ("apache", "tansu")


@dataclass(frozen=True)
class Variant:
    """One side of a comparison: its name and what its stack runs with."""

    name: str
    env: dict[str, str] = field(default_factory=dict)
    kafka: str | None = None  # None: as the command's --kafka says
    python: str | None = None  # None: this checkout's Python

    @classmethod
    def parse(cls, text: str) -> Variant:
        """`NAME=KEY=VALUE[,KEY=VALUE...]`; `kafka` and `python` are the variant's broker and
        interpreter, any other key a setting of the components (an environment variable)."""
        name, _, rest = text.partition("=")
        if not name or not name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(
                f"{text!r}: a variant starts with its name (letters, digits, - or _) and '='"
            )
        env: dict[str, str] = {}
        kafka = python = None
        for item in filter(None, rest.split(",")):
            key, sep, value = item.partition("=")
            if not sep or not key:
                raise ValueError(f"{text!r}: {item!r} is not KEY=VALUE")
            if key == "kafka":
                if value not in _BROKERS:
                    raise ValueError(
                        f"{text!r}: kafka is one of {', '.join(_BROKERS)}, not {value!r}"
                    )
                kafka = value
            elif key == "python":
                if not (Path(value).is_file() and os.access(value, os.X_OK)):
                    raise ValueError(f"{text!r}: {value} is not an executable Python")
                python = str(Path(value).absolute())
            else:
                env[key] = value
        return cls(name, env, kafka, python)


BROKER_VARIANTS = (Variant("apache", kafka="apache"), Variant("tansu", kafka="tansu"))
BROKER_NAMES = {"apache": "Apache Kafka", "tansu": "tansu"}


def run_rounds(
    args: Namespace,
    variants: tuple[Variant, Variant],
    base: Path,
    console: Any,
    run_once: Callable[..., dict[str, Any]],
) -> dict[str, list[dict[str, Any]]]:
    """`args.repeat` rounds, each a run per variant (the first variant alternating)."""
    runs: dict[str, list[dict[str, Any]]] = {v.name: [] for v in variants}
    for i in range(1, args.repeat + 1):
        order = variants if i % 2 else tuple(reversed(variants))
        for variant in order:
            run_dir = base / variant.name / f"run-{i}"
            shutil.rmtree(run_dir, ignore_errors=True)
            before = os.getloadavg()
            overrides: dict[str, Any] = {
                "stack_env": variant.env,
                "stack_python": variant.python,
                "variant_name": variant.name,  # names its --profile files
            }
            if variant.kafka is not None:
                overrides["kafka"] = variant.kafka
            result = run_once(
                Namespace(**{**vars(args), **overrides}), run_dir, i, args.repeat, console
            )
            result["variant"] = variant.name
            result["loadavg_before_run"] = before
            runs[variant.name].append(result)
            console.print(
                f"round {i}, {variant.name}: lost {result['lost']}, duplicated "
                f"{result['duplicated']}, p99 {_s(result.get('latency_p99_s'))}, "
                f"load {result['loadavg_1min_after_fleet']:.2f}"
            )
    return runs


def side_by_side(
    med: dict[str, dict[str, float]], names: tuple[str, str]
) -> list[tuple[str, dict[str, float | None]]]:
    """The compared measures, each with its median per variant (None: not measured)."""
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
        ("machine yardstick (ms)", "yardstick_ms"),
        ("load average (1 min) after the fleet", "loadavg_1min_after_fleet"),
    ]
    return [(label, {n: med.get(n, {}).get(key) for n in names}) for label, key in rows]


def ratio(values: dict[str, float | None], over: str, under: str) -> float | None:
    """`over`'s figure over `under`'s (None where either is missing or `under`'s is 0)."""
    a, b = values.get(over), values.get(under)
    if a is None or b is None or b == 0:
        return None
    return a / b


def _s(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f} s"


def _fmt(v: float | None) -> str:
    if v is None:
        return "n/a"
    return f"{v:,.0f}" if abs(v) >= 100 else f"{v:,.3g}"


def variants_of(args: Namespace) -> tuple[tuple[Variant, Variant], str, str]:
    """The two variants of the command, and which figure the ratio puts over which."""
    if args.kafka == "both":
        return BROKER_VARIANTS, "apache", "tansu"
    texts = list(args.compare or ())
    if len(texts) != 2:
        sys.exit(f"--compare is given twice, once per variant (given {len(texts)} times)")
    try:
        first, second = Variant.parse(texts[0]), Variant.parse(texts[1])
    except ValueError as e:
        sys.exit(f"--compare: {e}")
    if first.name == second.name:
        sys.exit(f"--compare: the two variants need two names (both are {first.name!r})")
    return (first, second), second.name, first.name


def main(args: Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

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
        sys.exit("a comparison runs one fleet size: drop --find-ceiling")
    variants, over, under = variants_of(args)
    names = (variants[0].name, variants[1].name)
    facts = machine_facts()
    with bench_data_dir(args.data_dir, "mapservice-compare-") as base:
        runs = run_rounds(args, variants, base, console, run_once)
    med = {name: medians(r) for name, r in runs.items()}
    rows = side_by_side(med, names)
    label = {n: BROKER_NAMES.get(n, n) if args.kafka == "both" else n for n in names}
    table = Table(
        title=f"mapservice bench ingest: {args.robots:,} robots, {args.seconds:.0f} s, MQTT "
        f"{args.mqtt}, median of {args.repeat} interleaved round(s)"
    )
    table.add_column("measure")
    for n in names:
        table.add_column(label[n], justify="right")
    table.add_column(f"{label[over]} / {label[under]}", justify="right")
    for measure, values in rows:
        r = ratio(values, over, under)
        table.add_row(
            measure, *(_fmt(values[n]) for n in names), "n/a" if r is None else f"{r:.2f}x"
        )
    console.print(table)
    facts["loadavg_at_end"] = os.getloadavg()
    doc = {
        "benchmark": "ingest, compared",
        "command": "mapservice " + " ".join(sys.argv[1:]),
        "args": {
            "robots": args.robots,
            "seconds": args.seconds,
            "mqtt": args.mqtt,
            "repeat": args.repeat,
            "data_dir": str(base),
        },
        "variants": [vars(v) for v in variants],
        "machine": facts,
        "side_by_side": [
            {"measure": measure, **values, f"{over}_over_{under}": ratio(values, over, under)}
            for measure, values in rows
        ],
        "medians": med,
        "runs": runs,
    }
    if args.json:
        Path(args.json).write_text(json.dumps(_json_safe(doc), indent=2, default=str))
        console.print(f"results written to {args.json}")
