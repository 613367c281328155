"""What a run stored: every row of the run window scanned through the API (lost and
duplicated events), and the bytes on disk after the parts are merged.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx

from mapservice.bench.ingest.probes import KEYS_PER_CHUNK, KEYS_PER_POSE, Key

API_LIMIT = 100_000  # the API's maximum `limit`


def _scan(client: httpx.Client, api_url: str, path: str, f: int, t: int) -> list[dict]:
    """Every row in [f, t), splitting the window when it would hit the API's limit."""
    r = client.get(f"{api_url}{path}", params={"from": f, "to": t, "limit": API_LIMIT})
    r.raise_for_status()
    body = r.json()
    if len(body) < API_LIMIT or t - f <= 1:
        return body
    mid = (f + t) // 2
    return _scan(client, api_url, path, f, mid) + _scan(client, api_url, path, mid, t)


def scan_run(api_url: str, f: int, t: int, slice_ms: int) -> dict[str, list[Key]]:
    out: dict[str, list[Key]] = {KEYS_PER_POSE: [], KEYS_PER_CHUNK: []}
    with httpx.Client(timeout=120) as client:
        for start in range(f, t, slice_ms):
            end = min(start + slice_ms, t)
            for kind, path in (
                (KEYS_PER_POSE, "/api/v1/poses"),
                (KEYS_PER_CHUNK, "/api/v1/chunk-events"),
            ):
                out[kind].extend(
                    (kind, row["robotId"], row["ts_ms"])
                    for row in _scan(client, api_url, path, start, end)
                )
    return out


def storage_report(data_dir: Path) -> dict:
    """Runs in a child process: chDB opens one directory per process."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.settings import Settings

    store = ClickHouseStore(Settings(data_dir=data_dir).resolved_clickhouse_dsn)
    db = store.database
    try:
        raw = {
            t: store.rows(f"SELECT count() FROM {db}.{t}", {})[0][0]
            for t in ("poses", "chunk_events", "chunk_contents")
        }
        parts_before = {
            t: int(n)
            for t, n in store.rows(
                "SELECT table, count() FROM system.parts WHERE database = {d:String} AND active "
                "GROUP BY table",
                {"d": db},
            )
        }
        store.optimize()
        merged = {
            t: store.rows(f"SELECT count() FROM {db}.{t}", {})[0][0]
            for t in ("poses", "chunk_events", "chunk_contents")
        }
        tables = store.storage_bytes()
        columns = _column_bytes(store, db)
    finally:
        store.close()
    return {
        "raw_rows_before_merge": raw,
        "rows_after_merge": merged,
        "active_parts_before_merge": parts_before,
        "table_bytes": tables,
        "column_compressed_bytes": columns,
    }


def _column_bytes(store, db: str) -> dict[str, dict[str, int]]:
    """Compressed bytes per column (diagnostic only, not counted in the totals).

    Short runs leave compact parts (all columns in one file), which report no per-column
    sizes, so the event tables are copied into a scratch database forced to wide parts.
    """
    scratch = "bench_scratch"
    with store.lock:
        c = store.client
        c.command(f"DROP DATABASE IF EXISTS {scratch}")
        c.command(f"CREATE DATABASE {scratch}")
        try:
            for t in ("poses", "chunk_events"):
                c.command(f"CREATE TABLE {scratch}.{t} AS {db}.{t}")
                c.command(
                    f"ALTER TABLE {scratch}.{t} MODIFY SETTING min_bytes_for_wide_part = 0, "
                    "min_rows_for_wide_part = 0"
                )
                c.command(f"INSERT INTO {scratch}.{t} SELECT * FROM {db}.{t}")
                c.command(f"OPTIMIZE TABLE {scratch}.{t} FINAL")
            rows = c.query(
                "SELECT table, column, sum(column_data_compressed_bytes), "
                "sum(column_data_uncompressed_bytes) FROM system.parts_columns "
                f"WHERE database = '{scratch}' AND active GROUP BY table, column"
            ).result_rows
        finally:
            c.command(f"DROP DATABASE IF EXISTS {scratch}")
    return {f"{t}.{col}": {"compressed": int(b), "uncompressed": int(u)} for t, col, b, u in rows}


def _storage_main(data_dir: str, out_file: str) -> None:
    Path(out_file).write_text(json.dumps(storage_report(Path(data_dir))))


def measure_storage(data_dir: Path) -> dict:
    out = data_dir / "storage.json"
    code = (
        "import sys; from mapservice.bench.ingest.storage import _storage_main; "
        "_storage_main(sys.argv[1], sys.argv[2])"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(data_dir), str(out)],
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"storage measurement failed:\n{done.stderr[-2000:]}")
    return json.loads(out.read_text())


def storage_figures(storage: dict, robots: int, seconds: float, result: dict) -> dict:
    """The bytes on disk after the merge, per robot-day (all tables, each table, the events
    alone) and per event."""
    total = sum(storage["table_bytes"].values())
    robot_days = robots * seconds / 86_400
    per_table = {t: b / robot_days for t, b in storage["table_bytes"].items()}
    events_only = sum(storage["table_bytes"].get(t, 0) for t in ("poses", "chunk_events"))
    return {
        **storage,
        "total_bytes": total,
        "robot_days": robot_days,
        "bytes_per_robot_day": total / robot_days,
        "bytes_per_robot_day_by_table": per_table,
        "bytes_per_robot_day_events_only": events_only / robot_days,
        "bytes_per_pose": storage["table_bytes"].get("poses", 0)
        / max(result["published_poses"], 1),
        "bytes_per_chunk_event": storage["table_bytes"].get("chunk_events", 0)
        / max(result["published_chunks"], 1),
    }
