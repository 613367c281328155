"""`mapservice bench ui`'s phases in headless Chromium: the page's seek times, frame times
and high-speed playback (stalls and skipped changes), read from and driven through the test
build's `window.__replay` hook.
"""

from __future__ import annotations

import json
import random
import time

from mapservice.bench.ui_expected import api_map, expected_at, mismatches


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


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
