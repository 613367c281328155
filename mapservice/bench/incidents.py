"""`mapservice bench incidents`: the CPU the live incident detection spends per pose
(mapservice/core/incident_tracker.py, as the processors run it), with a fleet of robots
driving about a floor, one pose a second each, fed as the history consumer feeds it: a
batch a second of every robot's pose. The robots wander at 0.5 m/s with a planned path, a
robot per `--floor-m2` square metres (so some pass close), a few stand still, a few run
their batteries down; CPU time of the detection only (process time around its calls).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from mapservice.core.incident_tracker import IncidentTracker
from mapservice.core.ports import PoseRow

T0 = 1_795_255_200_000
PATH = ((0.0, 0.0), (1.0, 1.0))


def run(robots: int, seconds: int, warm_s: int, floor_m2: float, seed: int = 1) -> dict[str, float]:
    """One run: µs of CPU per pose after `warm_s` seconds, and the incidents it found."""
    rng = random.Random(seed)
    side = math.sqrt(robots * floor_m2)
    fleet = [
        [rng.uniform(0, side), rng.uniform(0, side), rng.uniform(0, math.tau)]
        for _ in range(robots)
    ]
    tracker = IncidentTracker(lambda f, t, r: [], lambda f, t: [])
    spent, poses, found = 0.0, 0, 0
    for s in range(seconds):
        batch = []
        for i, robot in enumerate(fleet):
            standing = i % 50 == 0 and 60 <= s % 300 < 120
            if not standing:
                robot[2] += rng.uniform(-0.2, 0.2)
                robot[0] = min(side, max(0.0, robot[0] + 0.5 * math.cos(robot[2])))
                robot[1] = min(side, max(0.0, robot[1] + 0.5 * math.sin(robot[2])))
            battery = 80.0 - (s * 0.5 if i % 40 == 0 else 0.0)
            ts = T0 + s * 1000 + i % 1000
            batch.append(
                PoseRow(
                    f"robot-{i:05d}",
                    ts,
                    round(robot[0], 3),
                    round(robot[1], 3),
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    1.0,
                    max(battery, 1.0),
                    False,
                    None,
                    PATH,
                    ts,
                )
            )
        now = T0 + (s + 1) * 1000
        started = time.process_time()
        tracker.add(batch, now)
        tracker.tick(now)
        taken, retracted = tracker.take()
        tracker.forget(now)
        used = time.process_time() - started
        found += len(taken) + len(retracted)
        if s >= warm_s:
            spent += used
            poses += len(batch)
    return {"us_per_pose": spent / max(poses, 1) * 1e6, "poses": poses, "findings": found}


def main(args: argparse.Namespace) -> None:
    from rich.console import Console

    from mapservice.bench.machine import machine_facts
    from mapservice.bench.yardstick import yardstick_ms

    console = Console()
    if args.seconds <= args.warm_s:
        sys.exit("--seconds must be more than --warm-s (the figures come after the warm-up)")
    result: dict[str, Any] = {
        "machine": machine_facts(),
        "yardstick_ms": yardstick_ms(),
        "runs": {},
    }
    for robots in args.robots:
        rounds = []
        for k in range(args.rounds):
            console.print(f"{robots} robots, round {k + 1} of {args.rounds} ...")
            rounds.append(run(robots, args.seconds, args.warm_s, args.floor_m2, seed=k + 1))
        median = statistics.median(r["us_per_pose"] for r in rounds)
        result["runs"][robots] = {"rounds": rounds, "median_us_per_pose": median}
        console.print(
            f"{robots} robots: detection {median:.1f} µs of CPU per pose (median of "
            f"{args.rounds}; {rounds[0]['findings']} findings in the first)"
        )
    console.print(f"yardstick {result['yardstick_ms']:.1f} ms")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2, default=str))
        console.print(f"wrote {args.json}")


def add_parser(kinds: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    bench = kinds.add_parser(
        "incidents", help="the CPU per pose of the live incident detection, by fleet size"
    )
    bench.add_argument(
        "--robots", type=int, nargs="+", default=[200, 1000], help="fleet sizes to run"
    )
    bench.add_argument("--seconds", type=int, default=120, help="simulated seconds per run")
    bench.add_argument(
        "--warm-s", type=int, default=60, help="first seconds not counted (memory filling)"
    )
    bench.add_argument(
        "--floor-m2", type=float, default=100.0, help="square metres of floor per robot"
    )
    bench.add_argument("--rounds", type=int, default=3, help="runs per fleet size (median)")
    bench.add_argument("--json", default=None, help="write the runs as JSON to this file")
    bench.set_defaults(func=main)
