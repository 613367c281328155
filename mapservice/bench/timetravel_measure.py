"""`mapservice bench timetravel`'s measurement: each read timed beside its naive query and
checked equal to it, interleaved over random instants so noise hits every query alike,
and the other benchmarks that would skew the latencies watched for. Latencies are wall
time around the store call, in this process.
"""

from __future__ import annotations

import os
import random
import time

import numpy as np

from mapservice.bench.timetravel_naive import (
    naive_map_at,
    naive_poses_downsampled,
    naive_robots_at,
    naive_timeline,
)

DAY_MS = 86_400_000
HOUR_MS = 3_600_000
BUSY_PATTERNS = ("bench ingest", "exp.py", "tansu", "kafka.Kafka", "mosquitto")


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
