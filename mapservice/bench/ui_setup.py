"""`mapservice bench ui`'s set-up: the histories loaded with the bulk loader into embedded
ClickHouse (or reused from an earlier run's data directory, migrated to this release's
schema), and `mapservice api` serving one of them in a process of its own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from mapservice.local.checkout import TEST_UI_ENV
from mapservice.local.embedded import module_command


def api_env(chdb_dir: Path, database: str, port: int) -> dict[str, str]:
    """The environment of `mapservice api` over one chDB directory and database."""
    return {
        **os.environ,
        "MAPSERVICE_DATA_DIR": str(chdb_dir.parent),
        "MAPSERVICE_CLICKHOUSE_DSN": f"chdb://{chdb_dir.resolve()}",
        "MAPSERVICE_CLICKHOUSE_DATABASE": database,
        "MAPSERVICE_API_HOST": "127.0.0.1",
        "MAPSERVICE_API_PORT": str(port),
        "MAPSERVICE_FOXGLOVE_PORT": "0",  # a free one: benchmarks run beside other APIs
        "MAPSERVICE_LOG_LEVEL": "WARNING",
        # The benchmark measures the service, not its per-client rate limit (one browser
        # seeking and playing at full speed is one client).
        "MAPSERVICE_API_RATE_LIMIT": "",
        "PYTHONUNBUFFERED": "1",
        **TEST_UI_ENV,
    }


class ApiProcess:
    """`mapservice api` on a free port in its own process; the caller has closed the chDB
    directory first (one process may open it at a time). Stopped with SIGTERM on exit.
    `extra_env` overrides settings (a Foxglove port the caller knows, say)."""

    def __init__(
        self,
        chdb_dir: Path,
        database: str,
        log_path: Path,
        timeout_s: float = 120,
        extra_env: dict[str, str] | None = None,
    ) -> None:
        from mapservice.local.embedded import free_port

        self.port = free_port()
        self.env = {**api_env(chdb_dir, database, self.port), **(extra_env or {})}
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
                module_command("mapservice.cli", "api"),
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
