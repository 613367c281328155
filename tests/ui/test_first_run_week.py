"""A fresh `mapservice up` with its defaults (seven days of demo history) in Chromium: a seek
to the week's first hour, to two days ago and to an hour ago each draws every chunk of the
grid. The demo writes the map file at the week's first instant; nothing may expire it."""

from __future__ import annotations

from playwright.sync_api import TimeoutError as PlaywrightTimeout

from mapservice.adapters.ros_map import load_ros_map, slice_chunks
from tests.fixtures.paths import MAPS
from tests.fixtures.up import Up

TIMEOUT_MS = 90_000
HOUR_MS, DAY_MS = 3_600_000, 86_400_000


def week_up(data_dir) -> Up:
    """`mapservice up` with the default week of history: writing it takes a minute or two."""
    return Up(data_dir, ready_within_s=420)


def test_a_fresh_week_draws_the_whole_floor_at_every_seek(tmp_path, browser) -> None:
    grid = len(slice_chunks(load_ros_map(MAPS / "warehouse.yaml")))
    up = week_up(tmp_path / "data")
    api = f"http://127.0.0.1:{up.api_port}"
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(f"{api}/")
        page.wait_for_function(
            "() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS
        )
        now = page.evaluate("() => Date.now()")
        for back in (6 * DAY_MS + 23 * HOUR_MS, 2 * DAY_MS, HOUR_MS):
            page.goto(f"{api}/?t={now - back}")
            page.wait_for_function(
                "() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS
            )
            try:
                page.wait_for_function(
                    f"() => window.__replay.engine.state.cells.size === {grid}", timeout=30_000
                )
            except PlaywrightTimeout:
                pass
            drawn = page.evaluate("() => window.__replay.engine.state.cells.size")
            assert drawn == grid, f"{drawn} of {grid} chunks drawn {back / HOUR_MS:.0f} h back"
        assert errors == []
    finally:
        context.close()
        up.stop()
