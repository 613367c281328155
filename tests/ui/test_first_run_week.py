"""A fresh `mapservice up` with its defaults (seven days of demo history) in Chromium, one for
the module (writing the week takes a minute or two; both tests only read):

- a seek to the week's first hour, to two days ago and to an hour ago each draws every
  chunk of the grid (the demo writes the map file at the week's first instant; nothing may
  expire it);
- on the timeline's 7 d span the change feed lists the week's changes (no error, no "zoom
  in"), the map upload of the week's first instant is one upload mark, and the plots draw
  a robot's battery over the week."""

from __future__ import annotations

import pytest
from playwright.sync_api import TimeoutError as PlaywrightTimeout

from mapservice.adapters.ros_map import load_ros_map, slice_chunks
from tests.fixtures.paths import MAPS
from tests.fixtures.up import Up
from tests.ui.test_plots_timeline import iso

from .conftest import open_replay

pytestmark = pytest.mark.long

TIMEOUT_MS = 90_000
HOUR_MS, DAY_MS = 3_600_000, 86_400_000


@pytest.fixture(scope="module")
def up(tmp_path_factory):
    """`mapservice up` with the default week of history."""
    up = Up(tmp_path_factory.mktemp("week") / "data", ready_within_s=420)
    yield up
    up.stop()


def test_a_fresh_week_draws_the_whole_floor_at_every_seek(up, page) -> None:
    grid = len(slice_chunks(load_ros_map(MAPS / "warehouse.yaml")))
    api = f"http://127.0.0.1:{up.api_port}"
    open_replay(page, api, timeout_ms=TIMEOUT_MS)
    now = page.evaluate("() => Date.now()")
    for back in (6 * DAY_MS + 23 * HOUR_MS, 2 * DAY_MS, HOUR_MS):
        open_replay(page, api, f"?t={now - back}", timeout_ms=TIMEOUT_MS)
        try:
            page.wait_for_function(
                f"() => window.__replay.engine.state.cells.size === {grid}", timeout=30_000
            )
        except PlaywrightTimeout:
            pass
        drawn = page.evaluate("() => window.__replay.engine.state.cells.size")
        assert drawn == grid, f"{drawn} of {grid} chunks drawn {back / HOUR_MS:.0f} h back"
    assert page.errors == []


def test_a_fresh_weeks_7d_span_lists_changes_marks_the_upload_and_plots(up, page) -> None:
    api = f"http://127.0.0.1:{up.api_port}"
    open_replay(page, api, timeout_ms=TIMEOUT_MS)
    now = page.evaluate("() => Date.now()")
    span = (now - 7 * DAY_MS, now)
    robot = sorted(
        r["robotId"] for r in up.api("/api/v1/robots", at=now - 3_600_000).json()["robots"]
    )[0]
    open_replay(
        page,
        api,
        f"?t={now - 2 * DAY_MS}&sel={robot}&panels=changes,plots"
        f"&span={iso(span[0])},{iso(span[1])}",
        timeout_ms=TIMEOUT_MS,
    )
    # The change feed: the week's changes, newest first, read without an error.
    page.wait_for_function(
        "() => document.querySelectorAll('[data-testid=change-row][data-kind=change]').length > 0"
        " && !document.querySelector('[data-testid=change-count]').innerText.includes('loading')",
        timeout=TIMEOUT_MS,
    )
    assert page.locator('[data-testid="change-error"]').count() == 0
    shown = [
        int(t)
        for t in page.eval_on_selector_all(
            "[data-testid=change-row]", "rs => rs.map(r => r.dataset.ts)"
        )
    ]
    assert shown == sorted(shown, reverse=True) and span[0] <= shown[-1] and shown[0] < span[1]
    # The demo's map upload at the week's first instant: one mark, not a zoom-in note.
    page.wait_for_function(
        "() => document.querySelectorAll('[data-testid=upload-mark]').length > 0",
        timeout=TIMEOUT_MS,
    )
    assert "zoom in" not in page.inner_text(".timeline-bar")
    uploads = up.api(
        "/api/v1/changes", **{"from": span[0], "to": span[1], "kind": "upload", "limit": 1000}
    ).json()["changes"]
    assert uploads and any(u["robot_id"] == "map-upload" for u in uploads)
    marks = sorted(
        int(t)
        for t in page.eval_on_selector_all(
            "[data-testid=upload-mark]", "ms => ms.map(m => m.dataset.ts)"
        )
    )
    assert marks == sorted(u["ts_ms"] for u in uploads)
    # The plots: the selected robot's battery over the week.
    page.wait_for_function(
        f"() => {{ const p = window.__replay.plots(); return p && p.robots['{robot}']"
        f" && p.robots['{robot}'].mid.length > 100; }}",
        timeout=TIMEOUT_MS,
    )
    plot = page.evaluate(f"() => window.__replay.plots().robots['{robot}']")
    assert len({b for b in plot["battery"] if b is not None}) > 1
    assert page.errors == []
