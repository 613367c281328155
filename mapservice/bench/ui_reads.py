"""`mapservice bench ui`'s panel reads: the requests the plots and the timeline's upload
marks make, timed over HTTP against the API process (the page's own cost, drawing with
uPlot, is a few milliseconds and not what grows with the history).

For each span (1 h, 1 d, 7 d when the history is that long) and `n` random instants the
span ends at: a random robot's track as the plot panel asks for it (the step and start
`replay-ui/src/lib/plots.ts` picks for a 1280-pixel-wide page), the span's map uploads
(`/api/v1/changes?kind=upload`, the timeline's marks) and the change feed's first page.
A 422 (the span holds more writes than the change feed reads at once) is counted apart.
"""

from __future__ import annotations

import math
import random
import time
from typing import Any

KEYFRAME_MS = 60_000
PLOT_WIDTH_PX = 1264  # the plot panel's width in a 1280-pixel page
SPANS = {"1h": 3_600_000, "1d": 86_400_000, "7d": 7 * 86_400_000}


def plot_window(from_ms: int, to_ms: int, width_px: int = PLOT_WIDTH_PX) -> tuple[int, int]:
    """(start, step_ms) of the plot's track request: as plots.ts plotWindow."""
    raw = (to_ms - from_ms) / max(50, width_px / 2)
    step = (
        math.ceil(raw / KEYFRAME_MS) * KEYFRAME_MS
        if raw >= KEYFRAME_MS
        else max(1000, math.ceil(raw / 1000) * 1000)
    )
    start = from_ms // KEYFRAME_MS * KEYFRAME_MS if step % KEYFRAME_MS == 0 else from_ms
    return start, step


def percentile(values: list[float], q: float) -> float | None:
    """The nearest-rank percentile `q` of `values` (None without any), to 0.1."""
    if not values:
        return None
    s = sorted(values)
    return round(s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))], 1)


def latency_summary(values: list[float]) -> dict[str, Any]:
    """n, p50, p95 and max of milliseconds."""
    return {
        "n": len(values),
        "p50_ms": percentile(values, 50),
        "p95_ms": percentile(values, 95),
        "max_ms": percentile(values, 100),
    }


def panel_reads_phase(
    api_url: str, start_ms: int, end_ms: int, n: int, seed: int
) -> dict[str, Any]:
    import httpx

    rng = random.Random(seed)
    out: dict[str, Any] = {}
    with httpx.Client(base_url=api_url, timeout=600) as client:
        robots = [
            r["robotId"]
            for r in client.get("/api/v1/robots", params={"at": end_ms}).json()["robots"]
        ]
        for name, span in SPANS.items():
            if span > end_ms - start_ms:
                continue
            times: dict[str, list[float]] = {
                "plot_track": [],
                "uploads": [],
                "changes_first_page": [],
            }
            refused = dict.fromkeys(times, 0)
            points: list[int] = []
            for _ in range(n):
                to = rng.randint(start_ms + span, end_ms)
                f = to - span
                p_from, step = plot_window(f, to)
                asks: dict[str, tuple[str, dict[str, int | str]]] = {
                    "plot_track": (
                        f"/api/v1/robots/{rng.choice(robots)}/track",
                        {"from": p_from, "to": to + 1, "step_ms": step},
                    ),
                    "uploads": (
                        "/api/v1/changes",
                        {"from": f, "to": to, "kind": "upload", "limit": 1000},
                    ),
                    "changes_first_page": ("/api/v1/changes", {"from": f, "to": to, "limit": 100}),
                }
                for key, (path, params) in asks.items():
                    t0 = time.perf_counter()
                    r = client.get(path, params=params)
                    ms = (time.perf_counter() - t0) * 1000
                    if r.status_code == 422:
                        refused[key] += 1
                        continue
                    r.raise_for_status()
                    times[key].append(ms)
                    if key == "plot_track":
                        points.append(len(r.json()["points"]))
            out[name] = {
                k: {**latency_summary(v), "refused_422": refused[k]} for k, v in times.items()
            }
            out[name]["plot_track"]["points_p50"] = percentile([float(p) for p in points], 50)
            out[name]["plot_track"]["step_ms"] = plot_window(0, span)[1]
    return out
