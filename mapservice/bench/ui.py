"""`mapservice bench ui`: the replay UI measured in headless Chromium (Debian's, via Playwright).

Two histories are loaded with the bulk loader into embedded ClickHouse; each is then
served by `mapservice api` in a process of its own, as in production (no brokers needed for
replay), with the UI's test build (replay-ui/dist-test: the production page plus the
`window.__replay` hook the benchmark reads and drives). An API thread inside this process would share the GIL with Playwright's driver
and slow every answer the page waits for (until 2026-11-22 it was such a thread: seek times
measured before then include that contention).

- seek: `--days` of `--robots` robots; the page seeks to `--seeks` random instants and the
  time from the seek to the first complete frame (map and robots at T loaded, every
  chunk picture of the map drawn) is read from the page (`window.__replay.seekTimes`).
  The first seek (cold picture cache) is reported apart.
- panel reads (`--panel-reads`): the plots' track request, the timeline's upload marks and
  the change feed's first page over 1 h, 1 d and 7 d spans (mapservice/bench/ui_reads.py).
- incident reads (`--incident-reads`): the incidents panel's list for a day and the week and
  the week's heatmaps, each beside its naive query over the raw poses
  (mapservice/bench/incident_reads.py); the history's incidents are found first
  (incident_history.py). Without a browser phase (`--seeks 0 --high-speeds ""
  --play-seconds 0`) no browser and no UI build are needed.
- frames: `--frame-minutes` of `--frame-robots` robots; the page plays at 8x for
  `--play-seconds` and reports the script time of each animation frame (engine step,
  chunk drawing, robot markers) and the interval between frames.
- speeds (`--high-speeds`, default 3600x and 86400x, forward and backward): on the seek
  history the page plays for `--high-seconds` at each speed, with the server's chunk
  compaction (`chunk_step_ms`) and, for comparison, fetching every write
  (`--every-write`). Reported: every wait for the buffer while playing (`stalls`, the
  first apart as `startup_ms`: the buffer is empty after a seek), compared with one buffer
  window (`fetchSpanMs(speed) / speed` of wall time); and no skipped change: right at the
  pause the page's map must equal the map the API gives for what the page applied (the
  exact map at the last bucket boundary plus the current bucket's winners up to the
  playhead), the writes applied must number what the API says happened at that
  granularity, and after the seek in place the paused page does, the map must equal
  `map_at(playhead)` exactly.

`--data-dir DIR --reuse` loads each history once into DIR (a 200-robot week takes minutes,
its progress printed to stderr) and later runs reuse it while `DIR/loaded-<database>.json`
matches the arguments; a reused directory is migrated to this release's schema first (so
one history measures two releases back to back). The `summary` puts the seek p95 beside
the panel reads' p95 per span; `--baseline FILE` (an earlier run's `--json`) adds each
figure's ratio to that run's (this / baseline: under 1 is faster), the comparison that
holds on a shared machine where absolute times do not.

`--page-cpu-url URL` measures something else and only that: what an idle page costs,
Chromium's CPU live and paused on a running service with live robots, this build against
`--page-cpu-baseline` in interleaved pairs (ui_cpu.py).

The loading and the API process are in ui_setup.py, the browser phases in ui_browser.py,
what the page must show after playing in ui_expected.py, the panel reads in ui_reads.py.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from mapservice.bench.ui_browser import frame_phase, seek_phase, speeds_phase
from mapservice.bench.ui_cpu import add_arguments as add_page_cpu_arguments
from mapservice.bench.ui_setup import ApiProcess, load_or_reuse
from mapservice.bench.workdir import DATA_DIR_HELP
from mapservice.local.checkout import TEST_UI_DIR


def main(args) -> None:
    from mapservice.bench.machine import machine_facts
    from mapservice.bench.yardstick import yardstick_ms

    speeds = [int(s) for s in args.high_speeds.split(",") if s.strip()]
    browser = bool(args.seeks or speeds or args.play_seconds > 0 or args.page_cpu_url)
    if browser and not (TEST_UI_DIR / "index.html").exists():
        raise SystemExit(
            f"bench ui: the UI's test build ({TEST_UI_DIR}) is missing; run `make ui` first"
        )
    if args.page_cpu_url:
        from mapservice.bench.ui_cpu import main as page_cpu_main

        page_cpu_main(args)
        return
    if args.reuse and not args.data_dir:
        raise SystemExit("bench ui: --reuse needs --data-dir")
    tmp = Path(args.data_dir or tempfile.mkdtemp(prefix="bench-ui-"))
    tmp.mkdir(parents=True, exist_ok=True)
    end = time.time_ns() // 1_000_000 - 600_000
    out: dict = {
        "command": "mapservice " + " ".join(sys.argv[1:]),
        "machine": machine_facts(),
        "data_dir": str(tmp),
        "days": args.days,
        "robots": args.robots,
        "frame_robots": args.frame_robots,
        "frame_minutes": args.frame_minutes,
    }
    try:
        with _playwright(browser) as pw:
            t0 = time.perf_counter()
            result, reused = load_or_reuse(
                tmp, "bench_seek", args.days, args.robots, end, args.reuse
            )
            out["seek_history"] = {
                "poses": result.poses,
                "chunk_events": result.chunk_events,
                "load_s": round(time.perf_counter() - t0, 1),
                "reused": reused,
            }
            plan = None
            if args.incident_reads:
                from mapservice.bench.incident_history import find_or_reuse
                from mapservice.bench.incident_reads import plan_reads
                from mapservice.settings import Settings

                out["incidents_found"] = find_or_reuse(
                    tmp / "ch", "bench_seek", result.start_ms, result.end_ms
                )
                oldest = time.time_ns() // 1_000_000 - Settings().retention_ms + 60_000
                plan = plan_reads(
                    result.start_ms, result.end_ms, args.incident_reads, args.seed, oldest
                )
            out["yardstick_ms"] = yardstick_ms()
            out["loadavg_before"] = os.getloadavg()
            with ApiProcess(tmp / "ch", "bench_seek", tmp / "logs" / "api-seek.log") as api:
                if args.seeks:
                    out["seek"] = seek_phase(
                        pw, api.url, result.start_ms, result.end_ms, args.seeks, args.seed
                    )
                    print(json.dumps(out, indent=2), flush=True)
                if args.panel_reads:
                    from mapservice.bench.ui_reads import panel_reads_phase

                    out["panel_reads"] = panel_reads_phase(
                        api.url, result.start_ms, result.end_ms, args.panel_reads, args.seed
                    )
                    print(json.dumps(out["panel_reads"], indent=2), flush=True)
                if plan is not None:
                    from mapservice.bench.incident_reads import incident_reads_phase

                    out["incident_reads"] = incident_reads_phase(api.url, plan)
                    print(json.dumps(out["incident_reads"], indent=2), flush=True)
                if speeds:
                    out["speeds"] = speeds_phase(
                        pw,
                        api.url,
                        result.start_ms,
                        result.end_ms,
                        speeds,
                        args.high_seconds,
                        args.every_write,
                        not args.forward_only,
                    )
            if args.play_seconds > 0:
                result, _ = load_or_reuse(
                    tmp,
                    "bench_frames",
                    args.frame_minutes / 1440,
                    args.frame_robots,
                    end,
                    args.reuse,
                )
                with ApiProcess(tmp / "ch", "bench_frames", tmp / "logs" / "api-frames.log") as api:
                    out["frames"] = frame_phase(pw, api.url, result.start_ms, args.play_seconds)
        if plan is not None:
            out["incident_naive"] = naive_incident_reads(
                tmp / "ch", plan, args.incident_naive_reads, out["incidents_found"]
            )
        out["loadavg_after"] = os.getloadavg()
    finally:
        if not args.data_dir:
            shutil.rmtree(tmp, ignore_errors=True)
    out["summary"] = summary(out)
    if args.baseline:
        out["ratio_to_baseline"] = ratios(
            out["summary"], summary(json.loads(Path(args.baseline).read_text()))
        )
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


def summary(out: dict) -> dict:
    """Seek p95 beside the panel reads' p95 per span (the acceptance: plots and the change
    feed's first page within 300 ms p95 on a 200-robot week, seek within its target), and
    the incident reads' p95 beside their naive queries' (the week's within 300 ms)."""
    doc: dict = {"seek_p95_ms": out.get("seek", {}).get("p95_ms")}
    for span, reads in out.get("panel_reads", {}).items():
        for key in ("plot_track", "changes_first_page", "uploads"):
            if key in reads:
                doc[f"{key}_{span}_p95_ms"] = reads[key]["p95_ms"]
                doc[f"{key}_{span}_refused"] = reads[key]["refused_422"]
    reads, naive = out.get("incident_reads", {}), out.get("incident_naive", {})
    for key, naive_key in INCIDENT_FIGURES:
        if key in reads:
            doc[f"{key}_p95_ms"] = reads[key]["p95_ms"]
        if naive_key in naive:
            doc[f"naive_{key}_p95_ms"] = naive[naive_key]["p95_ms"]
    if reads:
        week = [reads[k]["p95_ms"] for k, _ in INCIDENT_FIGURES if k.endswith("_week")]
        doc["week_within_300_ms"] = max(week) <= INCIDENT_TARGET_MS
    return doc


# Each incident read's figure and the naive query it is set beside.
INCIDENT_FIGURES = (
    ("incidents_day", "incidents_day"),
    ("incidents_week", "incidents_week"),
    ("heatmap_occupancy_week", "heatmap_week"),
    ("heatmap_incidents_week", "incidents_week"),
)
INCIDENT_TARGET_MS = 300.0


@contextmanager
def _playwright(needed: bool) -> Iterator[Any]:
    """Playwright while a phase drives the browser; the API's reads alone need none."""
    if not needed:
        yield None
        return
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        yield pw


def naive_incident_reads(chdb_dir: Path, plan, repeats: int, found: dict) -> dict:
    """The naive queries of the incident reads, in this process once the API is gone."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.bench.incident_naive import naive_phase, recompute_estimate

    store = ClickHouseStore(f"chdb://{chdb_dir.resolve()}", database="bench_seek")
    try:
        doc = naive_phase(store, plan, repeats)
    finally:
        store.close()
    doc["recompute"] = recompute_estimate(found, found["end_ms"] - found["start_ms"])
    return doc


def ratios(now: dict, before: dict) -> dict:
    """Each p95 of `now` over the same figure of `before` (both measured on one history)."""
    return {
        k: round(v / before[k], 3)
        for k, v in now.items()
        if k.endswith("_ms")
        and isinstance(v, (int, float))
        and isinstance(before.get(k), (int, float))
        and before[k] > 0
    }


def add_parser(kinds) -> None:
    p = kinds.add_parser(
        "ui", help="the replay UI in headless Chromium: seek and frame times, an idle page's CPU"
    )
    p.add_argument("--days", type=float, default=7.0, help="history for the seek measurement")
    p.add_argument("--robots", type=int, default=20, help="simulated robots in the history")
    p.add_argument("--seeks", type=int, default=50, help="random seeks timed")
    p.add_argument(
        "--panel-reads",
        type=int,
        default=40,
        help="instants per span (1 h, 1 d, 7 d) at which the plots' track request, the timeline's "
        "upload marks and the change feed's first page are timed (0: none)",
    )
    p.add_argument(
        "--incident-reads",
        type=int,
        default=0,
        help="random days at which the incidents panel's list is timed, and as many times the "
        "week's list and the week's heatmaps (occupancy, incidents); the history's incidents "
        "are found first (0: none)",
    )
    p.add_argument(
        "--incident-naive-reads",
        type=int,
        default=3,
        help="times the naive queries over the week's raw poses run beside the incident reads",
    )
    p.add_argument(
        "--frame-robots",
        type=int,
        default=200,
        help="robots on the map for the frame-time measurement",
    )
    p.add_argument(
        "--frame-minutes",
        type=float,
        default=30.0,
        help="history minutes played for the frame-time measurement",
    )
    p.add_argument("--play-seconds", type=float, default=10.0, help="seconds of playback timed")
    p.add_argument("--seed", type=int, default=1, help="random seed of the history and the seeks")
    p.add_argument(
        "--high-speeds",
        default="3600,86400",
        help="speeds played on the seek history (comma-separated; empty: none)",
    )
    p.add_argument(
        "--high-seconds", type=float, default=5.0, help="seconds played at each high speed"
    )
    p.add_argument(
        "--every-write",
        action="store_true",
        help="also play each high speed fetching every chunk write (no compaction)",
    )
    p.add_argument("--forward-only", action="store_true", help="high speeds forwards only")
    p.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    p.add_argument(
        "--reuse",
        action="store_true",
        help="with --data-dir: load each history once, reuse it on later runs",
    )
    p.add_argument("--json", default=None, help="write the results as JSON to this file")
    add_page_cpu_arguments(p)
    p.add_argument(
        "--baseline",
        default=None,
        help="an earlier run's --json on the same history: report each p95's ratio to it",
    )
    p.set_defaults(func=main)
