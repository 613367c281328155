"""The naive counterparts of the incident reads (incident_reads.py): the same windows
answered from the raw poses, with no incidents table and no `heatmap_cells`, in this
process on a ClickHouseStore.

- incidents: a recomputation must read every pose of the window of every robot, and read
  the columns the rules read (robot, time, position, battery, charging, whether it has a
  path). `naive_incident_scan` reads exactly those, FINAL, and folds them per robot inside
  ClickHouse, so nothing crosses to Python: a lower bound of any recomputation, which would
  then carry the poses to Python and run the rules (`recompute_estimate` gives that full
  cost as the history's incidents took to find: hour windows through the store's `poses`
  and `detect`).
- heatmap: the heatmap rule over every pose of the window (heatmap_schema.samples_select:
  one sample per robot-second, its speed from the previous one, grouped by cell), what the
  heatmap read would cost if `heatmap_cells` did not exist. Its cells must equal the
  store's heatmap read (`heatmap_mismatches`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from mapservice.bench.incident_history import FoundIncidents
from mapservice.bench.incident_reads import ReadPlan
from mapservice.bench.ui_reads import latency_summary
from mapservice.core.heatmaps import HeatmapCell

if TYPE_CHECKING:
    from mapservice.adapters.clickhouse.store import ClickHouseStore

DAY_MS = 86_400_000


def naive_incident_scan(store: ClickHouseStore, from_ms: int, to_ms: int) -> list[Any]:
    """Per robot, a fold of every pose column the incident rules read over [from, to)."""
    from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS

    with store.lock:
        rows: list[Any] = store.client.query(
            "SELECT robot_id, count(), min(ts), max(ts), sum(x_mm), sum(y_mm), min(battery), "
            f"countIf(has_path), uniqExact(charging) FROM {store.database}.poses FINAL "
            "PREWHERE ts >= fromUnixTimestamp64Milli({f:Int64}) "
            "AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            f"GROUP BY robot_id ORDER BY robot_id {FINAL_SETTINGS}",
            parameters={"f": from_ms, "t": to_ms},
        ).result_rows
    return rows


def naive_heatmap(
    store: ClickHouseStore, from_ms: int, to_ms: int, factor: int = 1
) -> list[HeatmapCell]:
    """The heatmap's cells of `factor` finest cells a side from every pose of [from, to)."""
    from mapservice.adapters.clickhouse import heatmap_schema
    from mapservice.adapters.clickhouse.connection import FINAL_SETTINGS

    samples = heatmap_schema.samples_select(
        store.database, "{f:Int64}", "{t:Int64}", store.roles.heatmaps.heatmap_rule
    )
    with store.lock:
        rows = store.client.query(
            f"SELECT toInt32(floor({heatmap_schema.CELL_I} / {{k:Int32}})) AS ci, "
            f"toInt32(floor({heatmap_schema.CELL_J} / {{k:Int32}})) AS cj, "
            f"{heatmap_schema.SUMS} FROM ({samples}) GROUP BY ci, cj ORDER BY ci, cj "
            f"{FINAL_SETTINGS}",
            parameters={"f": from_ms, "t": to_ms, "k": factor},
        ).result_rows
    return [
        HeatmapCell(int(i), int(j), int(n), int(s), int(k), float(v)) for i, j, n, s, k, v in rows
    ]


def heatmap_mismatches(got: list[HeatmapCell], want: list[HeatmapCell]) -> int:
    """Cells that differ between two heatmaps (the speed sums to a relative 1e-9: summed in
    another order)."""
    a = {(c.i, c.j): c for c in got}
    b = {(c.i, c.j): c for c in want}
    bad = 0
    for key in a.keys() | b.keys():
        x, y = a.get(key), b.get(key)
        if x is None or y is None:
            bad += 1
        elif (x.samples, x.still, x.speeds) != (y.samples, y.still, y.speeds):
            bad += 1
        elif abs(x.speed_sum - y.speed_sum) > 1e-9 * max(1.0, abs(y.speed_sum)):
            bad += 1
    return bad


def naive_phase(store: ClickHouseStore, plan: ReadPlan, week_repeats: int) -> dict[str, Any]:
    """The naive queries over the plan's windows: the scan of each day, and of the week and
    the week's heatmap `week_repeats` times (each after one untimed run); then the week's
    heatmap from the store checked against the naive one."""
    times: dict[str, list[float]] = {"incidents_day": [], "incidents_week": [], "heatmap_week": []}

    def timed(key: str, fn: Callable[..., Any], *args: Any) -> Any:
        t0 = time.perf_counter()
        out = fn(*args)
        times[key].append((time.perf_counter() - t0) * 1000)
        return out

    wf, wt = plan.week
    naive_incident_scan(store, *plan.days[0])
    for f, t in plan.days:
        timed("incidents_day", naive_incident_scan, store, f, t)
    naive_incident_scan(store, wf, wt)
    for _ in range(week_repeats):
        timed("incidents_week", naive_incident_scan, store, wf, wt)
    want = naive_heatmap(store, wf, wt)
    for _ in range(week_repeats):
        timed("heatmap_week", naive_heatmap, store, wf, wt)
    got = store.heatmap_cells(wf, wt, 1)
    out: dict[str, Any] = {k: latency_summary(v) for k, v in times.items()}
    out["heatmap_check"] = {
        "cells": len(want),
        "mismatches": heatmap_mismatches(got, want),
        "samples": sum(c.samples for c in want),
        **prebuilt_share(store, wf, wt),
    }
    return out


def prebuilt_share(store: ClickHouseStore, from_ms: int, to_ms: int) -> dict[str, Any]:
    """How much of [from, to) the heatmap read takes from `heatmap_cells` (the whole
    10-minute buckets the snapshot builders wrote), the rest being read from the poses."""
    from mapservice.adapters.clickhouse import heatmap_schema

    b = heatmap_schema.BUCKET_MS
    with store.lock:
        ((rows, first, last),) = store.client.query(
            "SELECT count(), toUnixTimestamp64Milli(toDateTime64(min(bucket), 3)), "
            f"toUnixTimestamp64Milli(toDateTime64(max(bucket), 3)) FROM {store.database}."
            f"{heatmap_schema.TABLE} FINAL WHERE bucket >= toDateTime(intDiv({{f:Int64}}, 1000)) "
            "AND bucket < toDateTime(intDiv({t:Int64}, 1000))",
            parameters={"f": from_ms, "t": to_ms},
        ).result_rows
    covered = (int(last) + b - int(first)) if rows else 0
    return {"prebuilt_rows": int(rows), "prebuilt_share": round(covered / (to_ms - from_ms), 4)}


def recompute_estimate(found: FoundIncidents | dict[str, Any], history_ms: int) -> dict[str, float]:
    """What recomputing a day's and a week's incidents from the poses costs, as finding
    the history's took (reading its windows through the store and running the rules)."""
    doc = found if isinstance(found, dict) else vars(found)
    per_day = (doc["read_s"] + doc["detect_s"]) / max(history_ms / DAY_MS, 1e-9)
    return {"day_s": round(per_day, 1), "week_s": round(per_day * 7, 1)}
