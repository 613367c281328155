"""`bench ui`'s API in a process of its own (`mapservice api` over one chDB directory)."""

from __future__ import annotations

import time

import httpx
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.bench.ui import ApiProcess, api_env


def test_api_env_points_the_api_at_one_chdb_directory_and_database(tmp_path) -> None:
    """The environment names the chDB directory, the database and the port, on 127.0.0.1."""
    env = api_env(tmp_path / "ch", "bench_seek", 18080)
    assert env["MAPSERVICE_CLICKHOUSE_DSN"] == f"chdb://{(tmp_path / 'ch').resolve()}"
    assert env["MAPSERVICE_CLICKHOUSE_DATABASE"] == "bench_seek"
    assert (env["MAPSERVICE_API_HOST"], env["MAPSERVICE_API_PORT"]) == ("127.0.0.1", "18080")


def test_api_process_serves_until_exit_and_releases_the_directory(tmp_path) -> None:
    """The API answers once entered; after exit it is gone and this process may open the directory."""
    with ApiProcess(tmp_path / "ch", "bench_test", tmp_path / "api.log") as api:
        proc = api.proc
        now = time.time_ns() // 1_000_000
        r = httpx.get(f"{api.url}/api/v1/map", params={"at": now - 1000, "layout": "compact"})
        assert r.status_code == 200 and r.json()["cells"] == []
    assert proc.poll() is not None and api.proc is None
    with pytest.raises(httpx.HTTPError):
        httpx.get(f"{api.url}/readyz", timeout=2)
    store = ClickHouseStore(f"chdb://{tmp_path / 'ch'}", database="bench_test")
    try:
        assert store.counts().poses == 0  # the API created the schema; the lock is free again
    finally:
        store.close()


def test_api_process_that_exits_early_raises_naming_its_log(tmp_path, monkeypatch) -> None:
    """An API that cannot start raises at once with the path of its log, not after the timeout."""
    monkeypatch.setenv("MAPSERVICE_LOG_FORMAT", "no-such-format")  # a configuration error
    log = tmp_path / "api.log"
    with pytest.raises(RuntimeError, match=r"exited \(1\); see .*api\.log"):
        with ApiProcess(tmp_path / "ch", "bench_test", log, timeout_s=300):
            pass
    assert "configuration error" in log.read_text()
