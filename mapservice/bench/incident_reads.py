"""`mapservice bench ui --incident-reads N`: the incidents panel's list and the heatmap layer's
reads, timed over HTTP against the API process as the replay UI asks them, and beside each
the naive query over the raw poses of the same windows (incident_naive.py), run in this
process once the API has released the data directory.

- the incidents list (replay-ui/src/composables/useIncidents.ts): `GET /api/v1/incidents`
  with the timeline's span as from/to, no kind or robot filter, limit 5,000, for N random
  days and N times for the whole week (the history's span, at most seven days, from the
  oldest instant the page may ask for);
- the heatmap layer (composables/useHeatmap.ts): `GET /api/v1/heatmap` as PNG at the
  default cell (0.5 m), whose summary header is the legend, as the page asks before it
  draws; over the week, for occupancy and for the incidents kind. Beside it the JSON with
  every cell (an analyst's or a script's read, not the page's).

Every answer must be a 2xx: a failing API fails the benchmark.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Any

from mapservice.bench.ui_reads import latency_summary

DAY_MS = 86_400_000
WEEK_MS = 7 * DAY_MS
# The page's own figures (useIncidents.ts INCIDENT_LIMIT, lib/heatmap.ts DEFAULT_CELL_M,
# lib/retention.ts: the retention less a minute's margin).
INCIDENT_LIMIT = 5000
HEATMAP_CELL_M = 0.5
HEATMAP_KINDS = ("occupancy", "incidents")


@dataclass(frozen=True)
class ReadPlan:
    """The windows both the API's reads and the naive queries are timed over."""

    days: list[tuple[int, int]]
    week: tuple[int, int]

    @property
    def week_days(self) -> float:
        return (self.week[1] - self.week[0]) / DAY_MS


def plan_reads(start_ms: int, end_ms: int, n: int, seed: int, oldest_ms: int) -> ReadPlan:
    """N random days of [start, end) and its last week, none from before `oldest_ms` (the
    oldest instant the API keeps, as the page computes it); a history shorter than a day
    gives its whole span for each "day"."""
    first = max(start_ms, oldest_ms)
    if end_ms <= first or n < 1:
        raise ValueError("incident reads need history the API still keeps, read at least once")
    rng = random.Random(seed)
    span = min(DAY_MS, end_ms - first)
    days = []
    for _ in range(n):
        to = rng.randint(first + span, end_ms)
        days.append((to - span, to))
    return ReadPlan(days, (max(first, end_ms - WEEK_MS), end_ms))


def api_reads(client: Any, plan: ReadPlan) -> dict[str, Any]:
    """Times the page's requests through `client` (an httpx.Client on the API), once per
    day of the plan, after one round untimed (the first reads of a fresh process)."""

    def get(path: str, params: dict[str, Any]) -> tuple[float, Any]:
        t0 = time.perf_counter()
        r = client.get(path, params=params)
        ms = (time.perf_counter() - t0) * 1000
        r.raise_for_status()
        return ms, r

    times: dict[str, list[float]] = {"incidents_day": [], "incidents_week": []}
    for kind in HEATMAP_KINDS:
        times[f"heatmap_{kind}_week"], times[f"heatmap_{kind}_week_json"] = [], []
    listed: dict[str, list[int]] = {"incidents_day": [], "incidents_week": []}
    truncated = dict.fromkeys(listed, 0)
    cells: dict[str, int] = {}
    wf, wt = plan.week
    for i, day in enumerate([plan.days[0], *plan.days]):
        if i == 1:  # the warm-up round is not counted
            for v in times.values():
                v.clear()
            for n in listed.values():
                n.clear()
            truncated = dict.fromkeys(listed, 0)
        for key, (f, t) in (("incidents_day", day), ("incidents_week", plan.week)):
            ms, r = get("/api/v1/incidents", {"from": f, "to": t, "limit": INCIDENT_LIMIT})
            page = r.json()
            times[key].append(ms)
            listed[key].append(len(page["incidents"]))
            truncated[key] += bool(page["truncated"])
        for kind in HEATMAP_KINDS:
            params = {"kind": kind, "from": wf, "to": wt, "cell": HEATMAP_CELL_M, "format": "png"}
            png_ms, _ = get("/api/v1/heatmap", params)
            ms, r = get("/api/v1/heatmap", {**params, "format": "json"})
            times[f"heatmap_{kind}_week_json"].append(ms)
            times[f"heatmap_{kind}_week"].append(png_ms)
            cells[kind] = len(r.json()["cells"])
    out: dict[str, Any] = {k: latency_summary(v) for k, v in times.items()}
    for key in listed:
        out[key]["listed_max"] = max(listed[key], default=0)
        out[key]["truncated"] = truncated[key]
    for kind in HEATMAP_KINDS:
        out[f"heatmap_{kind}_week"]["cells"] = cells.get(kind, 0)
    return out


def incident_reads_phase(api_url: str, plan: ReadPlan) -> dict[str, Any]:
    """The page's reads against the API at `api_url`."""
    import httpx

    with httpx.Client(base_url=api_url, timeout=600) as client:
        return api_reads(client, plan)
