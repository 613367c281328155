"""`bench ui --incident-reads`: the history's incidents found window by window as `detect`
finds them over the whole history, the page's reads timed and failing with the API, and the
whole command on a tiny history (the API's answers beside the naive queries')."""

from __future__ import annotations

import json
import math
import random
import subprocess
import sys

import httpx
import pytest

from mapservice.bench.incident_history import find_incidents, find_or_reuse
from mapservice.bench.incident_naive import heatmap_mismatches
from mapservice.bench.incident_reads import DAY_MS, api_reads, plan_reads
from mapservice.core.heatmaps import HeatmapCell
from mapservice.core.incidents import detect
from mapservice.core.ports import PoseRow

T0 = 1_795_255_200_000
MIN_MS = 60_000
PATH = ((0.0, 0.0), (1.0, 1.0))


class History:
    """The reader's `poses` and the writer's `append_incidents` over a list of poses."""

    def __init__(self, poses: list[PoseRow]) -> None:
        self.rows = sorted(poses, key=lambda p: (p.ts_ms, p.robot_id))
        self.written: list = []
        self.found_at: list[int] = []

    def poses(self, from_ms, to_ms, robot_id=None, limit=100_000):
        return [p for p in self.rows if from_ms <= p.ts_ms < to_ms][:limit]

    def append_incidents(self, found, found_ms, retracted=()):
        self.written += found
        self.found_at.append(found_ms)


def pose(robot: str, ts: int, x: float, y: float, battery: float = 80.0) -> PoseRow:
    return PoseRow(robot, ts, x, y, 0.0, 0.0, 0.0, 0.0, 1.0, battery, False, None, PATH, ts)


def floor(seed: int, minutes: int, stuck_from: int, stuck_min: float) -> list[PoseRow]:
    """Five robots on 1 m circles a few metres apart (near misses as they pass), one that
    stops for `stuck_min` minutes from minute `stuck_from`, one whose battery runs low and
    one silent for 30 s, across the windows' edges."""
    rng = random.Random(seed)
    out = []
    for r in range(5):
        cx, cy, phase = rng.uniform(0, 4), rng.uniform(0, 4), rng.uniform(0, math.tau)
        for s in range(minutes * 60):
            ts = T0 + s * 1000 + r * 37
            if r == 2 and 599 <= s < 629:
                continue  # silent across the first window's edge
            if r == 0 and stuck_from * 60 <= s < (stuck_from + stuck_min) * 60:
                a = stuck_from * 60 * 0.2 + phase
            else:
                a = s * 0.2 + phase
            battery = 10.0 if r == 1 and 1190 <= s < 1250 else 80.0
            out.append(pose(f"r{r}", ts, cx + math.cos(a), cy + math.sin(a), battery))
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_windows_find_what_detect_finds_over_the_whole_history(seed) -> None:
    """Ten-minute windows (five-minute margins) write every incident `detect` finds over
    the whole history, once each, with the same bounds and evidence; each found at the end
    of what its window read."""
    history = History(floor(seed, 40, stuck_from=18, stuck_min=1.5))
    end = T0 + 40 * MIN_MS
    found = find_incidents(history, history, T0, end, window_ms=10 * MIN_MS, margin_ms=5 * MIN_MS)
    whole = detect(history.rows, end)
    assert {i.kind for i in whole} == {"near_miss", "stuck", "offline", "battery_low"}
    assert sorted(history.written, key=lambda i: (i.start_ms, i.kind, i.robots)) == whole
    assert found.total == len(whole) and found.cut == 0 and found.windows == 4
    assert found.by_kind == {k: sum(i.kind == k for i in whole) for k in found.by_kind}
    assert history.found_at == [T0 + 15 * MIN_MS, T0 + 25 * MIN_MS, T0 + 35 * MIN_MS, end]


def test_an_incident_longer_than_the_margin_is_written_once_as_found_there() -> None:
    """A robot stuck for 12 minutes from minute 8: its window keeps it as found 5 minutes
    after the window's end (ongoing there, counted as cut); the next windows leave it."""
    history = History(floor(4, 30, stuck_from=8, stuck_min=12))
    end = T0 + 30 * MIN_MS
    found = find_incidents(history, history, T0, end, window_ms=10 * MIN_MS, margin_ms=5 * MIN_MS)
    stuck = [i for i in history.written if i.kind == "stuck"]
    whole = {i.incident_id: i for i in detect(history.rows, end)}
    assert len(stuck) == 1 and stuck[0].incident_id in whole
    assert stuck[0].ongoing and stuck[0].end_ms < T0 + 15 * MIN_MS
    assert whole[stuck[0].incident_id].end_ms > T0 + 19 * MIN_MS
    # Every incident is written once; those it cut (the stuck one, and near misses of a
    # robot passing it) are the ones whose end the whole history puts later.
    assert sorted(i.incident_id for i in history.written) == sorted(whole)
    cut = [i for i in history.written if whole[i.incident_id].end_ms > i.end_ms]
    assert found.cut == len(cut) and stuck[0] in cut


def test_the_plan_reads_days_and_the_week_the_api_still_keeps() -> None:
    start, end = T0, T0 + 8 * DAY_MS
    plan = plan_reads(start, end, 20, seed=1, oldest_ms=T0 + DAY_MS // 2)
    assert plan.week == (end - 7 * DAY_MS, end) and plan.week_days == 7
    assert all(t - f == DAY_MS and f >= T0 + DAY_MS // 2 and t <= end for f, t in plan.days)
    short = plan_reads(T0, T0 + 3_600_000, 2, seed=1, oldest_ms=0)
    assert short.days == [(T0, T0 + 3_600_000)] * 2 and short.week == (T0, T0 + 3_600_000)
    with pytest.raises(ValueError, match="history the API still keeps"):
        plan_reads(T0, T0 + 3_600_000, 2, seed=1, oldest_ms=T0 + 3_600_000)


def fake_api(status: dict[str, int], asked: list[httpx.URL]) -> httpx.Client:
    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request.url)
        path, params = request.url.path, request.url.params
        code = status.get(path, 200)
        if path == "/api/v1/incidents":
            return httpx.Response(code, json={"incidents": [{"id": "a"}], "truncated": True})
        if params["format"] == "png":
            return httpx.Response(code, content=b"png")
        box = {"i0": 0, "j0": 0, "columns": 1, "rows": 1} if params["kind"] == "occupancy" else None
        return httpx.Response(code, json={"box": box, "cells": [[0, 0, 1.0]] if box else []})

    return httpx.Client(base_url="http://api", transport=httpx.MockTransport(answer))


def test_the_reads_ask_as_the_page_does_and_count_after_the_warm_up() -> None:
    """The list as the panel asks it (limit 5,000, no filter); the heatmap's PNG as the
    page asks it (its legend in its header), the JSON of every cell beside it; one untimed
    round first."""
    plan = plan_reads(T0, T0 + 8 * DAY_MS, 3, seed=2, oldest_ms=0)
    asked: list[httpx.URL] = []
    out = api_reads(fake_api({}, asked), plan)
    assert out["incidents_day"]["n"] == out["heatmap_occupancy_week"]["n"] == 3
    assert out["incidents_week"]["truncated"] == 3 and out["incidents_week"]["listed_max"] == 1
    assert out["heatmap_occupancy_week"]["cells"] == 1
    assert out["heatmap_incidents_week"]["cells"] == 0
    lists = [u for u in asked if u.path == "/api/v1/incidents"]
    assert len(lists) == 8 and {u.params["limit"] for u in lists} == {"5000"}
    assert not any("kind" in u.params or "robot" in u.params for u in lists)
    maps = [(u.params["kind"], u.params["format"]) for u in asked if u.path == "/api/v1/heatmap"]
    assert {m: maps.count(m) for m in set(maps)} == {
        (kind, form): 4 for kind in ("occupancy", "incidents") for form in ("png", "json")
    }
    assert {u.params["cell"] for u in asked if u.path == "/api/v1/heatmap"} == {"0.5"}


@pytest.mark.parametrize("path", ["/api/v1/incidents", "/api/v1/heatmap"])
def test_an_api_error_fails_the_reads(path) -> None:
    plan = plan_reads(T0, T0 + 2 * DAY_MS, 2, seed=2, oldest_ms=0)
    with pytest.raises(httpx.HTTPStatusError, match="500"):
        api_reads(fake_api({path: 500}, []), plan)


def test_heatmap_mismatches_count_cells_that_differ() -> None:
    a = [HeatmapCell(0, 0, 5, 1, 4, 0.8), HeatmapCell(1, 0, 2, 0, 2, 0.4)]
    assert heatmap_mismatches(a, list(a)) == 0
    assert heatmap_mismatches(a, [HeatmapCell(0, 0, 5, 1, 4, 0.8 + 1e-12), a[1]]) == 0
    assert heatmap_mismatches(a, [HeatmapCell(0, 0, 5, 2, 4, 0.8)]) == 2
    assert heatmap_mismatches(a, [a[0], HeatmapCell(1, 0, 2, 0, 2, 0.5)]) == 1


def test_the_command_times_the_reads_beside_the_naive_queries(tmp_path) -> None:
    """A tiny history through `bench ui` with only the incident reads (no browser): its
    incidents found and written, each read's figures beside its naive query's, and the
    heatmap from `heatmap_cells` equal to the one from every pose."""
    out = tmp_path / "incidents.json"
    command = [
        sys.executable,
        "-m",
        "mapservice.cli",
        "bench",
        "ui",
        *("--days", "0.05", "--robots", "6", "--seeks", "0", "--panel-reads", "0"),
        *("--high-speeds", "", "--play-seconds", "0", "--incident-reads", "2"),
        *("--incident-naive-reads", "1", "--data-dir", str(tmp_path / "data"), "--reuse"),
        *("--json", str(out)),
    ]
    subprocess.run(command, check=True, capture_output=True, timeout=300)
    doc = json.loads(out.read_text())
    found = doc["incidents_found"]
    assert found["total"] > 0 and set(found["by_kind"]) == {"near_miss"}
    assert not found["reused"] and found["poses_read"] >= doc["seek_history"]["poses"]
    reads, naive = doc["incident_reads"], doc["incident_naive"]
    assert reads["incidents_day"]["n"] == 2 and 0 < reads["incidents_week"]["listed_max"]
    assert reads["incidents_week"]["listed_max"] <= found["total"]
    assert reads["heatmap_occupancy_week"]["cells"] == naive["heatmap_check"]["cells"] > 0
    assert naive["heatmap_check"]["mismatches"] == 0
    # The loader built the snapshots, and with them the heatmap's 10-minute buckets.
    assert naive["heatmap_check"]["prebuilt_rows"] > 0
    assert 0.5 < naive["heatmap_check"]["prebuilt_share"] <= 1
    assert naive["heatmap_check"]["samples"] == doc["seek_history"]["poses"]
    assert naive["incidents_week"]["n"] == 1 and naive["recompute"]["day_s"] > 0
    assert doc["summary"]["heatmap_occupancy_week_p95_ms"] > 0
    assert doc["summary"]["naive_heatmap_occupancy_week_p95_ms"] > 0
    assert doc["yardstick_ms"] > 0 and doc["machine"]["git"]
    marker = json.loads((tmp_path / "data" / "incidents-bench_seek.json").read_text())
    assert marker["total"] == found["total"] and "reused" not in marker


def test_a_reused_directory_reads_back_its_incidents_without_searching(tmp_path) -> None:
    """The record beside the data names the loaded span: the same span is not searched
    again (the directory is not even opened)."""
    doc = {"start_ms": 1, "end_ms": 2, "total": 7, "by_kind": {"near_miss": 7}}
    (tmp_path / "incidents-bench_seek.json").write_text(json.dumps(doc))
    again = find_or_reuse(tmp_path / "no-such-dir", "bench_seek", 1, 2)
    assert again == {**doc, "reused": True}
