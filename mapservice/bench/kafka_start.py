"""`mapservice bench kafka-start`: the CPU and the time an embedded Apache Kafka node takes
from nothing to serving (its log formatted, then the broker until it answers a metadata
request), on the jars' class-data archive and without it (kafka_cds.py).

Each round starts one new node each way, alternating which goes first, so both see the
same load; the formatter's CPU is the children's CPU of this process around the format,
the broker's is read from /proc before it is stopped. Medians and the ratios of the
medians are reported. The archive is made first if there is none (not timed).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

WAYS = ("archive", "none")


def start_once(work_dir: Path, sharing: tuple[str, ...]) -> dict[str, Any]:
    """One new node started and stopped; its CPU and time to serving."""
    import psutil

    from mapservice.local import kafka_broker
    from mapservice.local.embedded import free_port

    config = kafka_broker.KafkaNodeConfig(
        log_dir=work_dir / "kafka" / "log", port=free_port(), controller_port=free_port()
    )
    java, libs = str(kafka_broker.java_binary()), kafka_broker.ensure_jars()
    started = time.monotonic()
    before = os.times()
    config_file = config.write_files()
    kafka_broker.format_once(java, libs, config_file, config.log_dir, sharing=sharing)
    after = os.times()
    formatted = time.monotonic()
    with open(work_dir / "kafka.log", "wb") as log_file:
        proc = kafka_broker.launch(config, log_file, sharing=sharing)
        try:
            kafka_broker.wait_ready(config, proc, timeout_s=120)
            served = time.monotonic()
            cpu = psutil.Process(proc.pid).cpu_times()
        finally:
            kafka_broker.stop_process_group(proc)
    return {
        "format_cpu_s": (after.children_user + after.children_system)
        - (before.children_user + before.children_system),
        "format_wall_s": formatted - started,
        "broker_cpu_s": cpu.user + cpu.system,
        "broker_wall_s": served - formatted,
        "cpu_s": (after.children_user + after.children_system)
        - (before.children_user + before.children_system)
        + cpu.user
        + cpu.system,
        "wall_s": served - started,
    }


def run(rounds: int, console: Console) -> dict[str, Any]:
    from mapservice.local import kafka_broker

    java, libs = str(kafka_broker.java_binary()), kafka_broker.ensure_jars()
    sharing = kafka_broker.class_sharing(java, libs, wait=True, progress=console.print)
    if not sharing:
        sys.exit("no class-data archive could be made (see the warning above)")
    results: list[dict[str, Any]] = []
    for i in range(rounds):
        for way in WAYS if i % 2 == 0 else tuple(reversed(WAYS)):
            with tempfile.TemporaryDirectory(prefix="bench-kafka-start-") as tmp:
                r = start_once(Path(tmp), sharing if way == "archive" else ())
            r.update(way=way, round=i + 1, load=os.getloadavg()[0])
            results.append(r)
            console.print(
                f"round {i + 1} {way:7s}: CPU {r['cpu_s']:.2f} s (format {r['format_cpu_s']:.2f}, "
                f"broker {r['broker_cpu_s']:.2f}), serving after {r['wall_s']:.1f} s "
                f"(load {r['load']:.1f})"
            )
    keys = ("cpu_s", "format_cpu_s", "broker_cpu_s", "wall_s")
    medians = {
        way: {k: statistics.median(r[k] for r in results if r["way"] == way) for k in keys}
        for way in WAYS
    }
    return {
        "kafka": kafka_broker.kafka_version(),
        "rounds": results,
        "medians": medians,
        "ratios": {k: medians["archive"][k] / medians["none"][k] for k in keys},
    }


def main(args: argparse.Namespace) -> None:
    from rich.console import Console

    from mapservice.bench.machine import machine_facts

    console = Console()
    if args.rounds < 1:
        sys.exit("--rounds must be at least 1")
    facts = machine_facts()
    result = run(args.rounds, console)
    facts["loadavg_at_end"] = os.getloadavg()
    result["machine"] = facts
    for way, m in result["medians"].items():
        console.print(
            f"{way:7s} (median of {args.rounds}): CPU {m['cpu_s']:.2f} s (format "
            f"{m['format_cpu_s']:.2f}, broker {m['broker_cpu_s']:.2f}), serving after "
            f"{m['wall_s']:.1f} s"
        )
    ratios = result["ratios"]
    console.print(
        f"archive / none: CPU {ratios['cpu_s']:.2f}, format {ratios['format_cpu_s']:.2f}, "
        f"broker {ratios['broker_cpu_s']:.2f}, time to serving {ratios['wall_s']:.2f}"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2, default=str))
        console.print(f"wrote {args.json}")


def add_parser(kinds: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    bench = kinds.add_parser(
        "kafka-start",
        help="the CPU and time of an embedded Apache Kafka node's start (format and "
        "broker), on the jars' class-data archive and without it",
    )
    bench.add_argument(
        "--rounds",
        type=int,
        default=5,
        help="rounds, each one start per way (alternating which goes first); medians "
        "and their ratios are reported",
    )
    bench.add_argument(
        "--json", default=None, help="write the rounds and medians as JSON to this file"
    )
    bench.set_defaults(func=main)
