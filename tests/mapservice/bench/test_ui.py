"""`bench ui`: its API in a process of its own (`mapservice api` over one chDB directory),
the reuse of a loaded history, and the skipped-change checks of its high-speed phase."""

from __future__ import annotations

import json
import random
import time

import httpx
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.bench import ui_expected, ui_setup
from mapservice.bench.ui_expected import expected_at, fold, mismatches
from mapservice.bench.ui_setup import ApiProcess, api_env, load_or_reuse
from mapservice.local.checkout import TEST_UI_DIR


def test_api_env_points_the_api_at_one_chdb_directory_and_database(tmp_path) -> None:
    """The environment names the chDB directory, the database and the port, on 127.0.0.1, and
    the UI's test build (the page with window.__replay, which the benchmark drives)."""
    env = api_env(tmp_path / "ch", "bench_seek", 18080)
    assert env["MAPSERVICE_UI_DIR"] == str(TEST_UI_DIR)
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


def test_fold_keeps_the_later_write_and_mismatches_count_cells_that_differ() -> None:
    """fold applies the page's rule (a late, older write loses); mismatches counts each differing cell."""
    base = {(0, 0): (10, "a", "h0")}
    writes = [
        {"row": 0, "column": 0, "ts_ms": 20, "robotId": "a", "content_hash": "h1"},
        {"row": 0, "column": 1, "ts_ms": 5, "robotId": "b", "content_hash": "h2"},
        {"row": 0, "column": 0, "ts_ms": 20, "robotId": "b", "content_hash": "h3"},
    ]
    state = fold(base, writes)
    assert state == {(0, 0): (20, "b", "h3"), (0, 1): (5, "b", "h2")}
    assert mismatches([[0, 0, 20, "b", "h3"], [0, 1, 5, "b", "h2"]], state) == 0
    assert mismatches([[0, 0, 20, "a", "h1"], [1, 1, 5, "b", "h2"]], state) == 3


def test_reuse_reads_back_the_loaded_history_and_refuses_another_size(tmp_path) -> None:
    """--reuse takes a matching history from its marker without loading; another size is refused."""
    marker = {"days": 7.0, "robots": 200, "poses": 5, "chunk_events": 3, "start_ms": 1, "end_ms": 2}
    (tmp_path / "loaded-bench_seek.json").write_text(json.dumps(marker))
    loaded, reused = load_or_reuse(tmp_path, "bench_seek", 7.0, 200, 99, reuse=True)
    assert reused and (loaded.start_ms, loaded.end_ms, loaded.chunk_events) == (1, 2, 3)
    with pytest.raises(SystemExit, match=r"7.0 days of 200 robots, not 7.0 of 20"):
        load_or_reuse(tmp_path, "bench_seek", 7.0, 20, 99, reuse=True)


@pytest.fixture
def served_history(ev, monkeypatch):
    """An API over a MemoryStore with random chunk writes; the bench's reads go to it."""
    from fastapi.testclient import TestClient

    from mapservice.adapters.clock import ManualClock
    from mapservice.api.app import create_app
    from mapservice.settings import Settings
    from mapservice.testing.memory_store import MemoryStore

    t0 = 1_795_255_200_000
    rng = random.Random(3)
    store = MemoryStore()
    store.append(
        [
            ev.chunk(
                rng.choice("abc"),
                t0 + rng.randrange(0, 3_600_000, 100),
                rng.randrange(3),
                rng.randrange(3),
                bytes([rng.randrange(256)]) * 10_000,
            )
            for _ in range(600)
        ]
    )
    client = TestClient(create_app(Settings(), store, {}, ManualClock(t0 + 7_200_000)))

    def get(api_url, path, **params):
        r = client.get(path, params=params)
        r.raise_for_status()
        return r.json()

    monkeypatch.setattr(ui_expected, "_get", get)
    return store, t0


def test_expected_state_at_a_bucket_boundary_is_the_exact_map_both_ways(served_history) -> None:
    """Played to just before a bucket boundary, forwards or backwards, the page must show
    map_at there, having crossed each bucket's winners in between."""
    store, t0 = served_history
    step = 300_000
    p0, p1 = t0 + 123_456, t0 + 10 * step - 1
    exact = {(c.row, c.column): (c.ts_ms, c.robot_id, c.content_hash) for c in store.map_at(p1)}
    state, crossed = expected_at("", p0, p1, step)
    assert state == exact
    assert len(crossed) == len(store.chunk_events_compacted(p0 + 1, p1 + 1, step)) > 0
    state, crossed = expected_at("", t0 + 3_400_000, p1, step)
    assert state == exact
    assert len(crossed) == len(store.chunk_events_compacted(p1 + 1, t0 + 3_400_001, step)) > 0
    state, crossed = expected_at("", p0, p1, 0)
    assert state == exact and len(crossed) == len(store.chunk_events(p0 + 1, p1 + 1))


def test_panel_reads_ask_for_the_track_as_the_plot_panel_does() -> None:
    """The benchmark's track request is the page's (replay-ui/tests/plots.test.ts has the
    same cases): about a sample every two pixels, whole seconds, and whole minutes from a
    whole minute over long spans."""
    from mapservice.bench.ui_reads import plot_window

    assert plot_window(0, 3_600_000, 1200) == (0, 6000)
    assert plot_window(0, 60_000, 1200) == (0, 1000)
    start = 1_795_255_242_005  # 2026-11-21T10:00:42.005Z
    assert plot_window(start, start + 7 * 86_400_000, 1000) == (start // 60_000 * 60_000, 1_260_000)
    assert plot_window(start, start + 3_600_000, 1200) == (start, 6000)


def test_summary_puts_panel_p95_beside_seek_and_ratios_compare_two_runs(capsys) -> None:
    from mapservice.bench import ui

    def run(seek: float, plot: float, feed: float) -> dict:
        return {
            "seek": {"p95_ms": seek},
            "panel_reads": {
                "1h": {
                    "plot_track": {"p95_ms": plot, "refused_422": 0},
                    "changes_first_page": {"p95_ms": feed, "refused_422": 1},
                }
            },
        }

    after, before = ui.summary(run(180.0, 50.0, 100.0)), ui.summary(run(200.0, 2500.0, None))
    assert after == {
        "seek_p95_ms": 180.0,
        "plot_track_1h_p95_ms": 50.0,
        "plot_track_1h_refused": 0,
        "changes_first_page_1h_p95_ms": 100.0,
        "changes_first_page_1h_refused": 1,
    }
    # A figure the baseline lacks (every request refused) has no ratio.
    assert ui.ratios(after, before) == {"seek_p95_ms": 0.9, "plot_track_1h_p95_ms": 0.02}
    for done in range(101):
        ui_setup._progress("load", done, 100, {"poses": done})
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 21 and lines[-1] == "bench ui: load 100/100 poses=100"
