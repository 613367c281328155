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

from mapservice.local.checkout import TEST_UI_DIR, TEST_UI_ENV

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
        **TEST_UI_ENV,
    }


class ApiProcess:
    """`mapservice api` on a free port in its own process; the caller has closed the chDB
    directory first (one process may open it at a time). Stopped with SIGTERM on exit."""

    def __init__(
        self, chdb_dir: Path, database: str, log_path: Path, timeout_s: float = 120
    ) -> None:
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
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "mapservice.cli", "api"],
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + self.timeout_s
        try:
            while True:
                if self.proc.poll() is not None:
                    raise RuntimeError(
                        f"the API exited ({self.proc.returncode}); see {self.log_path}"
                    )
                try:
                    if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                        return self
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the API was not ready within {self.timeout_s:.0f} s; see {self.log_path}"
                    )
                time.sleep(0.1)
        except BaseException:
            self.__exit__()
            raise

    def __exit__(self, *exc) -> None:
        from mapservice.local.embedded import stop

        stop(self.proc)
        self.proc = None


class Loaded:
    """What a load reports that the phases need (also read back from a reused directory)."""

    def __init__(self, poses: int, chunk_events: int, start_ms: int, end_ms: int) -> None:
        self.poses, self.chunk_events = poses, chunk_events
        self.start_ms, self.end_ms = start_ms, end_ms


def load_or_reuse(
    data: Path, database: str, days: float, robots: int, end_ms: int, reuse: bool
) -> tuple[Loaded, bool]:
    """Loads the history, or with `reuse` reads back the one loaded before with the same
    days and robots (its end then stays the first load's). Returns it and whether it was reused."""
    marker = data / f"loaded-{database}.json"
    if reuse and marker.exists():
        doc = json.loads(marker.read_text())
        if doc["days"] == days and doc["robots"] == robots:
            migrate(data / "ch", database)
            return Loaded(doc["poses"], doc["chunk_events"], doc["start_ms"], doc["end_ms"]), True
        raise SystemExit(
            f"bench ui: {marker} holds {doc['days']} days of {doc['robots']} "
            f"robots, not {days} of {robots}; use another --data-dir"
        )
    r = load(data / "ch", database, days, robots, end_ms)
    loaded = Loaded(r.poses, r.chunk_events, r.start_ms, r.end_ms)
    if reuse:
        marker.write_text(json.dumps({"days": days, "robots": robots, **vars(loaded)}))
    return loaded, False


def migrate(path: Path, database: str) -> None:
    """Brings a reused history to this release's schema (the API process only waits for it)."""
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
    from mapservice.adapters.clickhouse.store import ClickHouseStore

    store = ClickHouseStore(f"chdb://{path}", database=database)
    try:
        if store.schema_version() < SCHEMA_VERSION:
            t0 = time.perf_counter()
            print(
                f"bench ui: migrating {database} to schema {SCHEMA_VERSION}...",
                file=sys.stderr,
                flush=True,
            )
            store.migrate()
            print(
                f"bench ui: migrated in {time.perf_counter() - t0:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    finally:
        store.close()


_printed: dict[str, int] = {}


def _progress(phase: str, done: int, total: int, info: dict) -> None:
    """The loader's progress on stderr, about every 5 %."""
    twentieth = done * 20 // max(1, total)
    if _printed.get(phase) != twentieth:
        _printed[phase] = twentieth
        extra = "".join(f" {k}={v:,}" for k, v in info.items() if isinstance(v, int))
        print(f"bench ui: {phase} {done:,}/{total:,}{extra}", file=sys.stderr, flush=True)


def load(path: Path, database: str, days: float, robots: int, end_ms: int):
    """Both histories share one chDB directory, in two databases; closed once loaded."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.bench.history_loader import load_history
    from mapservice.robot import DEFAULT_MAP

    store = ClickHouseStore(f"chdb://{path}", database=database, snapshot_every_ms=600_000)
    try:
        return load_history(
            store,
            load_ros_map(DEFAULT_MAP),
            days=days,
            robots=robots,
            end_ms=end_ms,
            grid=(32, 48),
            on_progress=_progress,
        )
    finally:
        store.close()  # the API process opens the directory next


def browser_page(pw, url: str):
    from mapservice.testing.chromium import launch

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
    return {
        "first_seek_ms": first,
        "seeks": len(times),
        "p50_ms": percentile(times, 50),
        "p95_ms": percentile(times, 95),
        "max_ms": max(times),
        "images_downloaded": images,
        "api_part_p50_ms": percentile(api_times, 50),
        "api_part_p95_ms": percentile(api_times, 95),
    }


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
    return {
        "frames": len(script),
        "robots_shown": robots,
        "writes_applied": applied,
        "script_p50_ms": percentile(script, 50),
        "script_p95_ms": percentile(script, 95),
        "interval_p50_ms": percentile(intervals, 50),
        "interval_p95_ms": percentile(intervals, 95),
    }


def _get(api_url: str, path: str, **params):
    import httpx

    r = httpx.get(f"{api_url}{path}", params=params, timeout=600)
    r.raise_for_status()
    return r.json()


def api_map(api_url: str, at_ms: int) -> dict[tuple[int, int], tuple]:
    """The API's map at T: (row, column) -> (ts_ms, robotId, content_hash)."""
    doc = _get(api_url, "/api/v1/map", at=at_ms, layout="compact")
    i = [doc["fields"].index(f) for f in ("row", "column", "ts_ms", "robotId", "content_hash")]
    return {(c[i[0]], c[i[1]]): (c[i[2]], c[i[3]], c[i[4]]) for c in doc["cells"]}


def api_writes(api_url: str, f: int, t: int, step: int) -> list[dict]:
    """The API's chunk writes in [f, t) at one compaction step, over as many requests as the
    API's caps need (split on whole buckets, so no bucket is cut in two)."""
    out: list[dict] = []
    align = step or 60_000
    while f < t:
        end = min(t, (f + DAY_MS // 2) // align * align)
        end = end if end > f else min(t, f + DAY_MS // 2)
        doc = _get(
            api_url,
            "/api/v1/events",
            **{"from": f, "to": end, "step_ms": 3_600_000, "chunk_step_ms": step},
        )
        out.extend(doc["chunks"])
        f = doc["to_ms"] if doc["truncated"] else end
    return out


def fold(base: dict, writes: list[dict]) -> dict:
    """The page's rule: a write replaces the cell unless the cell shows a later one."""
    state = dict(base)
    for w in sorted(writes, key=lambda w: (w["ts_ms"], w["robotId"])):
        k = (w["row"], w["column"])
        if k not in state or (w["ts_ms"], w["robotId"]) >= state[k][:2]:
            state[k] = (w["ts_ms"], w["robotId"], w["content_hash"])
    return state


def expected_at(api_url: str, p0: int, p1: int, step: int) -> tuple[dict, list[dict]]:
    """What the page must show at p1 after playing from p0 (the map exact at p0), and the
    writes it must have applied (forwards) or undone (backwards) on the way, in the API's
    order.

    Every write (step 0): map_at(p1) and the writes between. Compacted: the buffer's windows
    end on whole buckets, so the page holds whole buckets [B, B+step) (cut only at p0 + 1,
    where its first window starts or ends); at p1 it shows the exact map before p1's bucket
    B plus that bucket's winners up to p1.
    """
    lo, hi = min(p0, p1), max(p0, p1)
    if step == 0:
        return api_map(api_url, p1), api_writes(api_url, lo + 1, hi + 1, 0)
    b = p1 // step * step
    if p1 > p0:
        start = max(b, p0 + 1)
        part = api_writes(api_url, start, b + step, step)
        whole = api_writes(api_url, p0 + 1, start, step) if start > p0 + 1 else []
        shown = [w for w in part if w["ts_ms"] <= p1]
        return fold(api_map(api_url, start - 1), shown), whole + shown
    top = min(b + step, p0 + 1)
    part = api_writes(api_url, b, top, step)
    above = api_writes(api_url, top, p0 + 1, step) if p0 + 1 > top else []
    shown = [w for w in part if w["ts_ms"] <= p1]
    return fold(api_map(api_url, b - 1), shown), [w for w in part if w["ts_ms"] > p1] + above


def mismatches(page_cells: list, expected: dict) -> int:
    page = {(c[0], c[1]): (c[2], c[3], c[4]) for c in page_cells}
    return sum(page.get(k) != expected.get(k) for k in page.keys() | expected.keys())


def speed_run(
    pw, api_url: str, at_ms: int, speed: int, direction: int, seconds: float, compact: bool
) -> dict:
    """Plays at `speed` from `at_ms` for `seconds`; stalls and the skipped-change checks."""
    browser, page = browser_page(pw, f"{api_url}/?t={at_ms}&speed={speed}")
    try:
        page.evaluate("(on) => window.__replay.setCompaction(on)", compact)
        page.evaluate("(t) => window.__replay.seek(t)", at_ms)
        page.wait_for_function(
            "() => window.__replay.complete && !window.__replay.seeking", timeout=120_000
        )
        p0 = page.evaluate("() => window.__replay.playhead")
        page.evaluate(
            "([s, d]) => { const r = window.__replay; r.clearCounts(); "
            "r.resetFrameStats(); r.play(s, d); }",
            [speed, direction],
        )
        time.sleep(seconds)
        # Paused and read in one script: before the next frame's seek in place.
        snap = page.evaluate(
            "() => { const r = window.__replay; r.pause(); return {"
            "playhead: r.playhead, cells: r.cells(), applied: r.applied, "
            "stalls: r.stalls.slice(), buffering: r.buffering, "
            "window_ms: r.bufferWindowMs, step: r.chunkStepMs, "
            "frames: r.frameIntervals.slice(), windows: r.windows.length}; }"
        )
        p1, step = snap["playhead"], snap["step"]
        page.wait_for_function(
            f"() => !window.__replay.seeking && "
            f"({step} === 0 || window.__replay.mapExactAt === window.__replay.playhead)",
            timeout=120_000,
        )
        rested = page.evaluate(
            "() => ({playhead: window.__replay.playhead, cells: window.__replay.cells()})"
        )
    finally:
        browser.close()
    expected, crossed = expected_at(api_url, p0, p1, step)
    stalls = snap["stalls"]
    startup, later = (stalls[0], stalls[1:]) if stalls else (0.0, [])
    applied = snap["applied"]["forward" if direction > 0 else "backward"]
    return {
        "speed": speed,
        "direction": direction,
        "compacted": compact,
        "chunk_step_ms": step,
        "played_s": seconds,
        "data_played_h": round(abs(p1 - p0) / 3_600_000, 2),
        "buffer_window_ms": round(snap["window_ms"]),
        "windows_fetched": snap["windows"],
        "startup_ms": round(startup),
        "stalls": len(later),
        "stall_max_ms": round(max(later, default=0)),
        "stall_total_ms": round(sum(later)),
        "stalls_over_window": sum(s > snap["window_ms"] for s in later),
        "buffering_at_pause": snap["buffering"],
        "frame_interval_p50_ms": percentile(snap["frames"], 50),
        "frame_interval_p95_ms": percentile(snap["frames"], 95),
        "changes_applied": applied,
        "changes_expected": len(crossed),
        "mismatching_cells": mismatches(snap["cells"], expected),
        "mismatching_cells_at_rest": mismatches(
            rested["cells"], api_map(api_url, rested["playhead"])
        ),
    }


def speeds_phase(
    pw,
    api_url: str,
    start_ms: int,
    end_ms: int,
    speeds: list[int],
    seconds: float,
    every_write: bool,
    backward: bool,
) -> list[dict]:
    runs = []
    for speed in speeds:
        for compact in [True, False] if every_write else [True]:
            runs.append(speed_run(pw, api_url, start_ms + 3_600_000, speed, 1, seconds, compact))
            print(json.dumps(runs[-1]), flush=True)
            if backward:
                runs.append(speed_run(pw, api_url, end_ms - 3_600_000, speed, -1, seconds, compact))
                print(json.dumps(runs[-1]), flush=True)
    return runs


def main(args) -> None:
    from playwright.sync_api import sync_playwright

    if not (TEST_UI_DIR / "index.html").exists():
        raise SystemExit(
            f"bench ui: the UI's test build ({TEST_UI_DIR}) is missing; run `make ui` first"
        )
    if args.reuse and not args.data_dir:
        raise SystemExit("bench ui: --reuse needs --data-dir")
    tmp = Path(args.data_dir or tempfile.mkdtemp(prefix="bench-ui-"))
    tmp.mkdir(parents=True, exist_ok=True)
    end = time.time_ns() // 1_000_000 - 600_000
    speeds = [int(s) for s in args.high_speeds.split(",") if s.strip()]
    out: dict = {
        "days": args.days,
        "robots": args.robots,
        "frame_robots": args.frame_robots,
        "frame_minutes": args.frame_minutes,
    }
    try:
        with sync_playwright() as pw:
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
    feed's first page within 300 ms p95 on a 200-robot week, seek within its target)."""
    doc: dict = {"seek_p95_ms": out.get("seek", {}).get("p95_ms")}
    for span, reads in out.get("panel_reads", {}).items():
        for key in ("plot_track", "changes_first_page", "uploads"):
            if key in reads:
                doc[f"{key}_{span}_p95_ms"] = reads[key]["p95_ms"]
                doc[f"{key}_{span}_refused"] = reads[key]["refused_422"]
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
    p = kinds.add_parser("ui", help="the replay UI in headless Chromium: seek and frame times")
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
    p.add_argument("--data-dir", default=None, help="default: a fresh temporary directory")
    p.add_argument(
        "--reuse",
        action="store_true",
        help="with --data-dir: load each history once, reuse it on later runs",
    )
    p.add_argument("--json", default=None, help="write the results as JSON to this file")
    p.add_argument(
        "--baseline",
        default=None,
        help="an earlier run's --json on the same history: report each p95's ratio to it",
    )
    p.set_defaults(func=main)
