"""The time-travel benchmark's report: its targets, the table printed on the console and the
section it appends to a Markdown journal (`--benchmarks-md`)."""

from __future__ import annotations

from typing import Any

TARGETS_MS = {
    "map_at": 100.0,
    "robots_at": 50.0,
    "window_10s": 50.0,
    "day_downsampled": 200.0,
    "timeline": 150.0,
    "track": None,
}

ROWS = [
    ("map_at(T), random T", "map_at:random", "naive_map:random", "map_at"),
    ("map_at(T), T in the last hour", "map_at:last_hour", "naive_map:last_hour", "map_at"),
    ("map_at(T), T ~6 days ago", "map_at:6_days_ago", "naive_map:6_days_ago", "map_at"),
    ("robots_at(T), random T", "robots_at", "naive_robots", "robots_at"),
    ("10 s window (chunk events + poses)", "window_10s", None, "window_10s"),
    (
        "one day, poses 1 per robot per --step-s",
        "day_downsampled",
        "naive_downsampled",
        "day_downsampled",
    ),
    (
        "one day for 86400x (1 per robot per 8,640 s)",
        "day_replay_86400x",
        "naive_replay_86400x",
        "day_downsampled",
    ),
    (
        "86400x, `from` off the minute (keyframes + heads)",
        "replay_86400x_any_from",
        None,
        "day_downsampled",
    ),
    ("timeline, whole history, 10-min buckets", "timeline_week", "naive_timeline_week", "timeline"),
    (
        "timeline, one day, 1,000 buckets of 86.4 s",
        "timeline_day",
        "naive_timeline_day",
        "timeline",
    ),
    ("track, one robot, one day at --step-s", "track_day", None, "track"),
]


def _fmt(v: float | None) -> str:
    return "-" if v is None else (f"{v:.0f}" if v >= 100 else f"{v:.1f}")


def table_rows(results: dict[str, Any]) -> list[list[str]]:
    lat = results["latency_ms"]
    out = []
    for label, key, naive, target in ROWS:
        s = lat[key]
        ns = lat[naive] if naive else {}
        goal = TARGETS_MS[target]
        if not s["n"]:
            continue
        out.append(
            [
                label,
                str(s["n"]),
                _fmt(s["p50"]),
                _fmt(s["p99"]),
                _fmt(s["max"]),
                _fmt(ns.get("p50")),
                _fmt(ns.get("p99")),
                "-" if goal is None else f"<= {goal:.0f}",
                "-" if goal is None else ("yes" if s["p99"] <= goal else "NO"),
            ]
        )
    return out


HEADER = ["query", "n", "p50 ms", "p99 ms", "max ms", "naive p50", "naive p99", "target p99", "met"]


def markdown(results: dict[str, Any]) -> str:
    info, m, checks = results["load"], results["machine"], results["measure"]["checks"]
    lat = results["measure"]["latency_ms"]
    lines = [
        "",
        f"## Time travel over a week of history ({results['finished'][:10]})",
        "",
        f"Command: `{results['command']}`",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['ram_gib']} GiB; Python {m['python']}, "
        f"chDB {m['chdb']} (embedded, in the benchmark's process) through clickhouse-connect "
        f"{m['clickhouse_connect']}.",
        "",
    ]
    meas = results["measure"]
    busy = results["busy_before"] + results["busy_after"] + meas.get("busy_seen", [])
    if busy:
        lines += [
            f"**The machine was not quiet**: another benchmark was running during "
            f"{meas.get('busy_rounds', '?')} of {meas.get('rounds', '?')} query rounds "
            f"(e.g. `{busy[0][:70]}`), so those latencies are pessimistic "
            f"(load average {results['loadavg_before']:.2f} before, "
            f"{results['loadavg_after']:.2f} after).",
            "",
        ]
    else:
        lines += [
            "No other benchmark ran during the measurement (checked every 10 query "
            f"rounds; load average {results['loadavg_before']:.2f} before, "
            f"{results['loadavg_after']:.2f} after).",
            "",
        ]
    if info.get("reused"):
        lines += ["The history was loaded by an earlier run (`--reuse`).", ""]
    lines += [
        f"History: {info.get('days')} days x {info.get('robots')} robots, one pose a second and "
        f"one chunk every five seconds each: {info.get('poses', 0):,} poses and "
        f"{info.get('chunk_events', 0):,} chunk events on a {info.get('grid', ['?'])[0]} x {info.get('grid', ['', '?'])[1]} "
        f"grid ({info.get('chunks', 0):,} chunks), {info.get('chunk_content_rows', 0):,} chunk "
        f"content rows ({info.get('distinct_contents', 0):,} distinct contents). "
        "maps/warehouse.yaml has 17 x 11 = 187 chunks; its chunks are re-sent at random cells "
        "of the 32 x 48 grid (as the 2019 load test re-sent chunks), and 1 % of the writes "
        "carry changed pixels. Robots drive 1 m circles around free cells of the map.",
        "",
        f"Load (`mapservice load-history`'s code): {info.get('load_s', 0):.1f} s to generate and "
        f"insert ({info.get('generate_s', 0):.1f} s numpy, {info.get('insert_s', 0):.1f} s "
        f"inserts), {(info.get('poses', 0) + info.get('chunk_events', 0)) / max(info.get('load_s', 1e-9), 1e-9):,.0f} "
        f"rows/s; snapshots every 10 min: {info.get('snapshots_one_by_one')} one by one in "
        f"{info.get('one_by_one_s', 0):.1f} s "
        f"({info.get('one_by_one_s', 0) / max(info.get('snapshots_one_by_one') or 1, 1) * 1000:.0f} ms "
        f"each, `build_snapshots`), the other {info.get('snapshots_bulk')} in "
        f"{info.get('bulk_s', 0):.1f} s (`build_snapshots_bulk`, one day per statement); "
        f"OPTIMIZE FINAL {info.get('optimize_s', 0):.1f} s"
        + (
            " (another benchmark was running during the load)."
            if info.get("busy_during_load")
            else " (no other benchmark ran during the load)."
        ),
        "",
        "| " + " | ".join(HEADER) + " |",
        "|" + "|".join(["---"] + ["---:"] * (len(HEADER) - 1)) + "|",
    ]
    for row in table_rows(results["measure"]):
        lines.append("| " + " | ".join(row) + " |")
    flat = lat["map_at:6_days_ago"]["p50"] / max(lat["map_at:last_hour"]["p50"], 1e-9)
    naive_flat = lat["naive_map:6_days_ago"]["p50"] / max(lat["naive_map:last_hour"]["p50"], 1e-9)
    lines += [
        "",
        f"Naive map: `SELECT row, col, argMax(content_hash, (ts, robot_id)) ... FROM chunk_events "
        f"WHERE ts <= T GROUP BY row, col`; naive robots: `SELECT robot_id, max(ts) FROM poses "
        f"WHERE ts <= T GROUP BY robot_id`. map_at p50 six days ago / in the last hour: "
        f"{flat:.2f} (naive: {naive_flat:.2f}).",
        f"Correctness: map_at(T) equal to the naive query for {checks['map_at_compared']} "
        f"instants, mismatches = {checks['map_at_mismatches']}; robots_at(T) equal to the naive "
        f"query for {checks['robots_compared']}, mismatches = {checks['robots_mismatches']}. "
        f"Downsampled days (from pose_keyframes) equal to the same answer from every pose "
        f"(the 'naive' column) for {checks.get('downsampled_compared', 0)} windows, "
        f"mismatches = {checks.get('downsampled_mismatches', '?')}. Timelines equal to the "
        f"same buckets counted from every event for {checks.get('timeline_compared', 0)}, "
        f"mismatches = {checks.get('timeline_mismatches', '?')}. "
        f"Downsampled day: step {results['measure']['step_ms']} ms, at most "
        f"{checks['downsampled_rows_max']:,} poses returned; 10 s windows returned up to "
        f"{checks['window_rows']} rows; the whole-history timeline has "
        f"{checks.get('week_buckets', '?')} buckets.",
    ]
    if results.get("storage"):
        parts = ", ".join(
            f"{k} {v / 2**20:.1f} MiB" for k, v in sorted(results["storage"].items()) if v > 2**20
        )
        lines += [f"On disk after merging: {parts}."]
    if results.get("remarks"):
        lines += ["", *results["remarks"]]
    return "\n".join(lines) + "\n"
