"""`mapservice bench ui --page-cpu-url URL`: what a replay page left open costs the machine
while nothing happens on it, as Chromium's CPU (% of one core, from psutil over the
browser's process tree: browser, renderer, GPU and utility processes).

The page is opened on a running service with live robots (say `mapservice up --robots 2
--history-days 0`), 1280x800 in headless Chromium, and left alone for `--page-cpu-load-seconds`
(its first seek, pictures and reads); then its CPU is read over `--page-cpu-seconds`, twice:
live (no `t` in the address) and paused ten minutes back (`?t=`).

The page's files (index.html, its scripts) are served from a build directory by the
browser itself (Playwright's routing; the API and the live stream still go to the
service), so one service measures two builds: `--page-cpu-baseline DIR` (say main's
`replay-ui/dist-test`) alternates with this checkout's test build, pair by pair, and the
report gives each build's medians and their ratio (this / baseline): on a shared machine
the ratio holds where absolute figures drift.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

import psutil

from mapservice.bench.procstat import cpu_seconds

if TYPE_CHECKING:
    from playwright.sync_api import Page, Playwright, Route

PAUSED_BACK_MS = 600_000
MODES = ("live", "paused")


def _browser_root(before: set[int]) -> psutil.Process:
    """The Chromium just launched: this process's descendant named chrom* that was not
    there before and whose parent is not Chromium (Playwright's driver starts it)."""
    for p in psutil.Process().children(recursive=True):
        try:
            if p.pid in before or not p.name().startswith("chrom"):
                continue
            parent = p.parent()
            if parent is None or not parent.name().startswith("chrom"):
                return p
        except psutil.Error:
            continue
    raise RuntimeError("bench ui: the launched Chromium's process was not found")


def _serve_build(page: Page, ui_dir: Path) -> None:
    """The page's own files from `ui_dir`; everything under /api/ from the service."""

    def fulfil(route: Route) -> None:
        path = urlparse(route.request.url).path
        f = ui_dir / (path.lstrip("/") or "index.html")
        if f.is_file():
            route.fulfill(path=str(f))
        else:
            route.continue_()

    page.route(lambda url: "/api/" not in urlparse(url).path, fulfil)


def page_cpu(
    pw: Playwright, url: str, ui_dir: Path, query: str, load_s: float, seconds: float
) -> dict[str, float]:
    """One fresh browser with one page of `ui_dir`'s build at `url` + `query`: Chromium's
    CPU over `seconds` (% of a core), after `load_s` of loading."""
    from mapservice.testing.chromium import launch

    before = {p.pid for p in psutil.Process().children(recursive=True)}
    browser = launch(pw)
    try:
        root = _browser_root(before)
        page = browser.new_context(viewport={"width": 1280, "height": 800}).new_page()
        _serve_build(page, ui_dir)
        page.goto(f"{url.rstrip('/')}/{query}")
        time.sleep(load_s)
        c0, w0 = cpu_seconds(root), time.monotonic()
        time.sleep(seconds)
        c1, w1 = cpu_seconds(root), time.monotonic()
    finally:
        browser.close()
    return {"cpu_pct": round(100 * (c1 - c0) / (w1 - w0), 2), "wall_s": round(w1 - w0, 1)}


def page_cpu_phase(
    pw: Playwright,
    url: str,
    builds: dict[str, Path],
    pairs: int,
    load_s: float,
    seconds: float,
) -> dict[str, Any]:
    """`pairs` rounds; in each, every build live then paused, the builds' order alternating
    from one round to the next (a drift of the machine weighs on both alike)."""
    for name, d in builds.items():
        if not (d / "index.html").is_file():
            raise SystemExit(f"bench ui: {d} holds no built page ({name}); run `make ui` there")
    runs: dict[str, dict[str, list[float]]] = {n: {m: [] for m in MODES} for n in builds}
    rounds = []
    names = list(builds)
    for i in range(pairs):
        order = names if i % 2 == 0 else names[::-1]
        got: dict[str, dict[str, float]] = {}
        for mode in MODES:
            for name in order:
                query = (
                    "" if mode == "live" else f"?t={time.time_ns() // 1_000_000 - PAUSED_BACK_MS}"
                )
                r = page_cpu(pw, url, builds[name], query, load_s, seconds)
                runs[name][mode].append(r["cpu_pct"])
                got.setdefault(name, {})[mode] = r["cpu_pct"]
                print(
                    f"bench ui: page cpu round {i + 1} {name} {mode}: {r['cpu_pct']} %", flush=True
                )
        rounds.append(got)
    medians = {n: {m: statistics.median(v) for m, v in by.items()} for n, by in runs.items()}
    out: dict[str, Any] = {
        "url": url,
        "builds": {n: str(d) for n, d in builds.items()},
        "load_s": load_s,
        "seconds": seconds,
        "paused_back_ms": PAUSED_BACK_MS,
        "rounds": rounds,
        "median_cpu_pct": medians,
    }
    if "baseline" in builds and "this" in builds:
        out["ratio_this_to_baseline"] = {
            m: round(medians["this"][m] / medians["baseline"][m], 3)
            for m in MODES
            if medians["baseline"][m] > 0
        }
        out["pair_ratios"] = [
            {m: round(r["this"][m] / r["baseline"][m], 3) for m in MODES if r["baseline"][m] > 0}
            for r in rounds
        ]
    return out


def main(args: argparse.Namespace) -> None:
    """The `--page-cpu-url` mode of `bench ui`: no history loaded, only the pages measured."""
    import json

    from playwright.sync_api import sync_playwright

    from mapservice.bench.machine import machine_facts
    from mapservice.bench.yardstick import yardstick_ms
    from mapservice.local.checkout import TEST_UI_DIR

    builds = {"this": TEST_UI_DIR}
    if args.page_cpu_baseline:
        builds = {"baseline": Path(args.page_cpu_baseline), "this": TEST_UI_DIR}
    out: dict[str, Any] = {"machine": machine_facts(), "yardstick_ms_before": yardstick_ms()}
    with sync_playwright() as pw:
        out["page_cpu"] = page_cpu_phase(
            pw,
            args.page_cpu_url,
            builds,
            args.page_cpu_pairs,
            args.page_cpu_load_seconds,
            args.page_cpu_seconds,
        )
    out["yardstick_ms_after"] = yardstick_ms()
    out["load_average_end"] = list(psutil.getloadavg())
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--page-cpu-url",
        default=None,
        help="measure only an idle page's Chromium CPU, live and paused, on the service at "
        "this URL (one with live robots: `mapservice up --robots 2 --history-days 0`); no "
        "history is loaded",
    )
    p.add_argument(
        "--page-cpu-seconds", type=float, default=20.0, help="seconds each page's CPU is read"
    )
    p.add_argument(
        "--page-cpu-load-seconds",
        type=float,
        default=10.0,
        help="seconds each page loads before its CPU is read",
    )
    p.add_argument(
        "--page-cpu-pairs", type=int, default=3, help="rounds (each build live and paused)"
    )
    p.add_argument(
        "--page-cpu-baseline",
        default=None,
        metavar="DIR",
        help="another build of the page (say main's replay-ui/dist-test) measured in turn "
        "with this checkout's: medians of each and their ratio",
    )
