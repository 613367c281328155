"""The verdict of the fault tests (test_faults.py, test_kafka_cluster_faults.py), once the
load of fault_load.py and its faults are over: per fault, every acknowledged message stored
once (published, acknowledged, stored, duplicated, lost, recovery times); the latest map the
fold of the stored chunk history, every snapshot the fold at its instant. The report is
written to test-artifacts/faults.json."""

from __future__ import annotations

import json
import time

import httpx

from mapservice.core.ports import ChunkRow
from mapservice.core.timetravel import fold_map
from tests.fixtures.paths import ROOT

from .fault_load import FaultRun, Load, Sent, Sql, now_ms, stored_identities

ARTIFACT = ROOT / "test-artifacts" / "faults.json"
REPORT: dict = {}  # both tests' sections, rewritten to ARTIFACT after each


def count_of(stored: dict, s: Sent) -> int:
    value = stored.get(s.key, 0)
    return value[0] if isinstance(value, tuple) else value


def wait_all_stored(
    sql: Sql, load: Load, segments: list[str], timeout_s: float = 90, settled_s: float = 8
) -> None:
    """Until every acknowledged message's identity is stored, or nothing new was stored for
    `settled_s` (what tansu lost stays lost), or the timeout; the report counts what is
    missing then as lost."""
    want = {s.key for s in load.sent if s.acknowledged}
    deadline = time.monotonic() + timeout_s
    seen, since = -1, time.monotonic()
    while time.monotonic() < deadline:
        try:
            poses, chunks = stored_identities(sql, segments, final=True)
            have = set(poses) | set(chunks)
            if want <= have:
                return
            if len(have) != seen:
                seen, since = len(have), time.monotonic()
            elif time.monotonic() - since >= settled_s:
                return
        except Exception:  # noqa: BLE001 - busy or just restarted: ask again
            pass
        time.sleep(1)


def api_duplicates(api_url: str, load: Load, segments: list[str]) -> dict[str, int]:
    """Rows the API's history reads return beyond one per identity, per segment."""
    lo, hi = min(s.key[-1] for s in load.sent) - 1, max(s.key[-1] for s in load.sent) + 1
    poses = httpx.get(
        f"{api_url}/api/v1/poses", timeout=60, params={"from": lo, "to": hi, "limit": 100_000}
    ).json()
    chunks = httpx.get(
        f"{api_url}/api/v1/chunk-events",
        timeout=60,
        params={"from": lo, "to": hi, "limit": 100_000},
    ).json()
    out = {}
    for seg in segments:
        keys = [(p["robotId"], p["ts_ms"]) for p in poses if p["robotId"].startswith(f"{seg}-")]
        ckeys = [
            (c["row"], c["column"], c["robotId"], c["ts_ms"])
            for c in chunks
            if c["robotId"].startswith(f"{seg}-")
        ]
        out[seg] = (len(keys) - len(set(keys))) + (len(ckeys) - len(set(ckeys)))
    return out


def segment_report(
    run: FaultRun,
    sent: list[Sent],
    final: tuple[dict, dict],
    raw: tuple[dict, dict],
    api_dups: dict[str, int],
) -> dict:
    def table(s: Sent, pair: tuple[dict, dict]) -> dict:
        return pair[0] if s.kind == "pose" else pair[1]

    acked = [s for s in sent if s.acknowledged]
    lost = [s for s in acked if not count_of(table(s, final), s)]
    return {
        "fault": run.name,
        "published": len(sent),
        "acknowledged": len(acked),
        "stored": sum(1 for s in sent if count_of(table(s, final), s)),
        # Rows every read sees beyond one per identity: FINAL in SQL, and the API's replies.
        "duplicated": sum(max(0, count_of(table(s, final), s) - 1) for s in sent)
        + api_dups.get(run.name, 0),
        # Re-delivered rows not merged yet (ReplacingMergeTree folds them; reads use FINAL).
        "raw_duplicate_rows": sum(max(0, count_of(table(s, raw), s) - 1) for s in sent),
        "lost": len(lost),
        "lost_published_after_restart": sum(1 for s in lost if s.sent_ms >= run.restarted_ms),
        "wrong_content": sum(
            1
            for s in acked
            if s.kind == "chunk" and s.key in final[1] and final[1][s.key][1] != s.content_hash
        ),
        "down_s": round((run.restarted_ms - run.killed_ms) / 1000, 2) if run.killed_ms else None,
        "recovery_s": (
            round((run.recovered_ms - run.killed_ms) / 1000, 2) if run.recovered_ms else None
        ),
        # From the fault until every acknowledged message of its robots was stored (None:
        # some never were).
        "caught_up_s": (
            round((run.caught_up_ms - run.killed_ms) / 1000, 2) if run.caught_up_ms else None
        ),
    }


def all_chunk_rows(sql: Sql) -> list[ChunkRow]:
    return [
        ChunkRow(row, col, ts, robot, h, 0)
        for row, col, ts, robot, h in sql(
            "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)) "
            "FROM mapservice.chunk_events FINAL"
        )
    ]


def wait_snapshot_repairs_done(sql: Sql, timeout_s: float = 60) -> int:
    """Late arrivals (a fault delays messages past a snapshot) note repairs; the snapshot
    timer works them off. Returns how many are still pending."""
    deadline, pending = time.monotonic() + timeout_s, -1
    while time.monotonic() < deadline:
        (pending,) = sql("SELECT count() FROM mapservice.snapshot_repairs")[0]
        if pending == 0:
            return 0
        time.sleep(1)
    return pending


def check_snapshots(sql: Sql, rows: list[ChunkRow]) -> tuple[list[int], list[int]]:
    """Each stored snapshot against the fold of the stored history at its instant: the map
    per chunk, the robots per robot (its latest pose time). Returns (all, wrong) instants."""
    snaps = [
        t
        for (t,) in sql(
            "SELECT toUnixTimestamp64Milli(snap_ts) FROM "
            "mapservice.snapshot_log FINAL ORDER BY snap_ts"
        )
    ]
    pose_times = sql(
        "SELECT robot_id, groupArray(toUnixTimestamp64Milli(ts)) "
        "FROM mapservice.poses FINAL GROUP BY robot_id"
    )
    wrong = []
    for t in snaps:
        stored = {
            (row, col): (ts, robot, h)
            for row, col, ts, robot, h in sql(
                "SELECT row, col, toUnixTimestamp64Milli(ts), robot_id, lower(hex(content_hash)) "
                "FROM mapservice.map_snapshots FINAL WHERE snap_ts = fromUnixTimestamp64Milli({t:Int64})",
                t=t,
            )
        }
        want = {k: (s.ts_ms, s.robot_id, s.content_hash) for k, s in fold_map(rows, t).items()}
        robots = dict(
            sql(
                "SELECT robot_id, toUnixTimestamp64Milli(ts) FROM mapservice.robot_snapshots "
                "FINAL WHERE snap_ts = fromUnixTimestamp64Milli({t:Int64})",
                t=t,
            )
        )
        want_robots = {r: max(x for x in ts if x <= t) for r, ts in pose_times if min(ts) <= t}
        if stored != want or robots != want_robots:
            wrong.append(t)
    return snaps, wrong


def map_reads_wrong(api_url: str, rows: list[ChunkRow], instants: list[int]) -> list[int]:
    """The API's map at each instant against the fold: the instants where they differ."""
    wrong = []
    for t in instants:
        got = {
            (c["row"], c["column"]): (c["ts_ms"], c["robotId"], c["content_hash"])
            for c in httpx.get(f"{api_url}/api/v1/map", params={"at": t}, timeout=60).json()[
                "chunks"
            ]
        }
        want = {k: (s.ts_ms, s.robot_id, s.content_hash) for k, s in fold_map(rows, t).items()}
        if got != want:
            wrong.append(t)
    return wrong


def verify(sql: Sql, api_url: str, load: Load, runs: list[FaultRun], merge: bool) -> dict:
    """The per-fault counts and the whole-history checks, once everything settled."""
    segments = [r.name for r in runs] + ["warmup", "after"]
    wait_all_stored(sql, load, segments)
    final, raw = stored_identities(sql, segments, True), stored_identities(sql, segments, False)
    dups = api_duplicates(api_url, load, segments)
    runs = runs + [FaultRun("warmup"), FaultRun("after")]
    faults = [segment_report(run, load.of(run.name), final, raw, dups) for run in runs]
    # The latest map (the API's map at now) and each snapshot against folds of the stored
    # history, once the repairs the faults' late arrivals caused are done.
    pending = wait_snapshot_repairs_done(sql)
    rows = all_chunk_rows(sql)
    snaps, wrong_snaps = check_snapshots(sql, rows)
    checks = {
        "latest_map_equals_fold": not map_reads_wrong(api_url, rows, [now_ms()]),
        "snapshots": len(snaps),
        "wrong_snapshots": wrong_snaps,
        "map_reads_at_snapshots_wrong": map_reads_wrong(
            api_url, rows, snaps[:: max(1, len(snaps) // 8)]
        ),
        "snapshot_repairs_pending": pending,
    }
    if merge:
        # Re-delivered rows are merged away: after a merge, one row per identity.
        sql("OPTIMIZE TABLE mapservice.poses FINAL")
        sql("OPTIMIZE TABLE mapservice.chunk_events FINAL")
        merged = stored_identities(sql, segments, False)
        checks["raw_duplicates_after_merge"] = sum(
            max(0, (v[0] if isinstance(v, tuple) else v) - 1) for d in merged for v in d.values()
        )
    return {"faults": faults, "checks": checks}


def write_report(section: str, report: dict) -> None:
    REPORT[section] = report
    ARTIFACT.parent.mkdir(parents=True, exist_ok=True)
    ARTIFACT.write_text(json.dumps(REPORT, indent=2) + "\n")
    print(f"\n{section}: {report['topology']}")
    print(
        f"{'fault':<28}{'published':>10}{'acked':>8}{'stored':>8}{'dup':>5}{'raw dup':>8}"
        f"{'lost':>6}{'back s':>8}{'recovery s':>11}{'caught up s':>12}"
    )
    for r in report["faults"]:
        print(
            f"{r['fault']:<28}{r['published']:>10}{r['acknowledged']:>8}{r['stored']:>8}"
            f"{r['duplicated']:>5}{r['raw_duplicate_rows']:>8}{r['lost']:>6}{r['down_s']!s:>8}"
            f"{r['recovery_s']!s:>11}{r['caught_up_s']!s:>12}"
        )
    print(json.dumps(report["checks"]), flush=True)


def assert_guarantees(report: dict, lossy: set[str]) -> None:
    """What can be promised: no duplicate and no wrong content anywhere; no acknowledged
    message lost, except through tansu's memory storage (faults in `lossy`), where still
    nothing published after the new Kafka was up may be lost; every fault recovered and
    caught up; the latest map and every snapshot equal the fold of the history."""
    for r in report["faults"]:
        assert r["duplicated"] == 0 and r["wrong_content"] == 0, r
        assert r["acknowledged"] > 0.9 * r["published"], r
        assert r["lost"] == 0 or r["fault"] in lossy, r
        assert r["lost_published_after_restart"] == 0, r
        assert r["recovery_s"] is not None or r["fault"] in ("warmup", "after"), r
        # Every acknowledged message of the fault stored before the next fault began.
        assert r["caught_up_s"] is not None or r["fault"] in lossy | {"warmup", "after"}, r
    checks = report["checks"]
    assert checks["latest_map_equals_fold"], checks
    assert checks["snapshots"] >= 3 and not checks["wrong_snapshots"], checks
    assert not checks["map_reads_at_snapshots_wrong"], checks
    assert checks["snapshot_repairs_pending"] == 0, checks
    assert checks.get("raw_duplicates_after_merge", 0) == 0, checks
