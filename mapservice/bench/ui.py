"""`mapservice bench ui`: the replay UI measured in headless Chromium (Debian's, via Playwright).

Two histories are loaded with the bulk loader into embedded ClickHouse; each is then
served by `mapservice api` in a process of its own, as in production (no brokers needed for
replay). An API thread inside this process would share the GIL with Playwright's driver
and slow every answer the page waits for (until 2026-11-22 it was such a thread: seek times
measured before then include that contention).

- seek: `--days` of `--robots` robots; the page seeks to `--seeks` random instants and the
  time from the seek to the first complete frame (map and robots at T loaded, every
  chunk picture of the map drawn) is read from the page (`window.__replay.seekTimes`).
  The first seek (cold picture cache) is reported apart.
- frames: `--frame-minutes` of `--frame-robots` robots; the page plays at 8x for
  `--play-seconds` and reports the script time of each animation frame (engine step,
  chunk drawing, robot markers) and the interval between frames.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mapservice.local.checkout import UI_INDEX

DAY_MS = 86_400_000


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


def api_env(chdb_dir: Path, database: str, port: int) -> dict[str, str]:
    """The environment of `mapservice api` over one chDB directory and database."""
    return {
        **os.environ,
        "MAPSERVICE_DATA_DIR": str(chdb_dir.parent),
        "MAPSERVICE_CLICKHOUSE_DSN": f"chdb://{chdb_dir.resolve()}",
        "MAPSERVICE_CLICKHOUSE_DATABASE": database,
        "MAPSERVICE_API_HOST": "127.0.0.1",
        "MAPSERVICE_API_PORT": str(port),
        "MAPSERVICE_LOG_LEVEL": "WARNING",
        # The benchmark measures the service, not its per-client rate limit (one browser
        # seeking and playing at full speed is one client).
        "MAPSERVICE_API_RATE_LIMIT": "",
        "PYTHONUNBUFFERED": "1",
    }


class ApiProcess:
    """`mapservice api` on a free port in its own process; the caller has closed the chDB
    directory first (one process may open it at a time). Stopped with SIGTERM on exit."""

    def __init__(self, chdb_dir: Path, database: str, log_path: Path,
                 timeout_s: float = 120) -> None:
        from mapservice.local.embedded import free_port

        self.port = free_port()
        self.env = api_env(chdb_dir, database, self.port)
        self.log_path = log_path
        self.timeout_s = timeout_s
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> ApiProcess:
        import httpx

        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "mapservice.cli", "api"],
                                         env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        deadline = time.monotonic() + self.timeout_s
        try:
            while True:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"the API exited ({self.proc.returncode}); see {self.log_path}")
                try:
                    if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                        return self
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the API was not ready within {self.timeout_s:.0f} s; "
                                       f"see {self.log_path}")
                time.sleep(0.1)
        except BaseException:
            self.__exit__()
            raise

    def __exit__(self, *exc) -> None:
        from mapservice.local.embedded import stop

        stop(self.proc)
        self.proc = None


def load(path: Path, database: str, days: float, robots: int, end_ms: int):
    """Both histories share one chDB directory, in two databases; closed once loaded."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.bench.history_loader import load_history
    from mapservice.robot import DEFAULT_MAP
    from mapservice.adapters.ros_map import load_ros_map

    store = ClickHouseStore(f"chdb://{path}", database=database, snapshot_every_ms=600_000)
    try:
        return load_history(store, load_ros_map(DEFAULT_MAP), days=days, robots=robots,
                            end_ms=end_ms, grid=(32, 48))
    finally:
        store.close()  # the API process opens the directory next


def browser_page(pw, url: str):
    from mapservice.local.chromium import launch

    browser = launch(pw)
    page = browser.new_context(viewport={"width": 1280, "height": 800}).new_page()
    page.goto(url)
    page.wait_for_function("() => window.__replay && window.__replay.complete", timeout=120_000)
    return browser, page


def seek_phase(pw, api_url: str, start_ms: int, end_ms: int, seeks: int, seed: int) -> dict:
    rng = random.Random(seed)
    browser, page = browser_page(pw, f"{api_url}/?t={end_ms - 60_000}")
    try:
        first = page.evaluate("() => window.__replay.seekTimes[0]")
        times = []
        for _ in range(seeks):
            t = rng.randrange(start_ms + 60_000, end_ms - 60_000)
            n = page.evaluate("() => window.__replay.seekTimes.length")
            page.evaluate("(t) => window.__replay.seek(t)", t)
            page.wait_for_function(f"() => window.__replay.seekTimes.length > {n}", timeout=120_000)
            times.append(page.evaluate("() => window.__replay.seekTimes.at(-1)"))
        images = page.evaluate("() => window.__replay.fetchedImages")
        api_times = page.evaluate("() => window.__replay.seekApiTimes.slice(1)")
    finally:
        browser.close()
    return {"first_seek_ms": first, "seeks": len(times), "p50_ms": percentile(times, 50),
            "p95_ms": percentile(times, 95), "max_ms": max(times), "images_downloaded": images,
            "api_part_p50_ms": percentile(api_times, 50), "api_part_p95_ms": percentile(api_times, 95)}


def frame_phase(pw, api_url: str, start_ms: int, play_seconds: float) -> dict:
    browser, page = browser_page(pw, f"{api_url}/?t={start_ms + 60_000}&speed=8")
    try:
        page.evaluate("() => { window.__replay.resetFrameStats(); window.__replay.play(8, 1); }")
        time.sleep(play_seconds)
        page.evaluate("() => window.__replay.pause()")
        script = page.evaluate("() => window.__replay.frameTimes.slice()")
        intervals = page.evaluate("() => window.__replay.frameIntervals.slice()")
        robots = page.evaluate("() => window.__replay.robots().length")
        applied = page.evaluate("() => window.__replay.log.length")
    finally:
        browser.close()
    return {"frames": len(script), "robots_shown": robots, "writes_applied": applied,
            "script_p50_ms": percentile(script, 50), "script_p95_ms": percentile(script, 95),
            "interval_p50_ms": percentile(intervals, 50),
            "interval_p95_ms": percentile(intervals, 95)}


def main(args) -> None:
    from playwright.sync_api import sync_playwright

    if not UI_INDEX.exists():
        raise SystemExit("bench ui: the UI is not built; run `make ui` first")
    tmp = Path(args.data_dir or tempfile.mkdtemp(prefix="bench-ui-"))
    end = time.time_ns() // 1_000_000 - 600_000
    out: dict = {"days": args.days, "robots": args.robots, "frame_robots": args.frame_robots,
                 "frame_minutes": args.frame_minutes}
    try:
        with sync_playwright() as pw:
            t0 = time.perf_counter()
            result = load(tmp / "ch", "bench_seek", args.days, args.robots, end)
            out["seek_history"] = {"poses": result.poses, "chunk_events": result.chunk_events,
                                   "load_s": round(time.perf_counter() - t0, 1)}
            with ApiProcess(tmp / "ch", "bench_seek", tmp / "logs" / "api-seek.log") as api:
                out["seek"] = seek_phase(pw, api.url, result.start_ms, result.end_ms,
                                         args.seeks, args.seed)
            print(json.dumps(out, indent=2), flush=True)
            result = load(tmp / "ch", "bench_frames", args.frame_minutes / 1440,
                          args.frame_robots, end)
            with ApiProcess(tmp / "ch", "bench_frames", tmp / "logs" / "api-frames.log") as api:
                out["frames"] = frame_phase(pw, api.url, result.start_ms, args.play_seconds)
    finally:
        if not args.data_dir:
            shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


def add_parser(kinds) -> None:
    p = kinds.add_parser("ui", help="the replay UI in headless Chromium: seek and frame times")
    p.add_argument("--days", type=float, default=7.0, help="history for the seek measurement")
    p.add_argument("--robots", type=int, default=20, help="simulated robots in the history")
    p.add_argument("--seeks", type=int, default=50, help="random seeks timed")
    p.add_argument("--frame-robots", type=int, default=200, help="robots on the map for the frame-time measurement")
    p.add_argument("--frame-minutes", type=float, default=30.0, help="history minutes played for the frame-time measurement")
    p.add_argument("--play-seconds", type=float, default=10.0, help="seconds of playback timed")
    p.add_argument("--seed", type=int, default=1, help="random seed of the history and the seeks")
    p.add_argument("--data-dir", default=None, help="default: a fresh temporary directory")
    p.add_argument("--json", default=None, help="write the results as JSON to this file")
    p.set_defaults(func=main)
