"""What a newcomer meets first, in Chromium: a fresh `mapservice up` shows the real floor at
once and a past to replay; two days ago the robots stand on free floor, drawn online.

The history written here is 2.1 days (the default is 7: ~85 s on this machine, too long to
spend in every CI run); the code path is the same. The screenshot it takes is the README's
(`docs/screenshot.png`, rewritten only with MAPSERVICE_UPDATE_SCREENSHOTS=1).
"""

from __future__ import annotations

import io
import os

import httpx
import numpy as np
from PIL import Image

from mapservice.adapters.ros_map import drivable, load_ros_map, slice_chunks
from mapservice.core.wire2019 import content_hash
from mapservice.robot.chunks import meta_from_json, metres_to_pixel
from tests.fixtures.paths import MAPS, ROOT
from tests.fixtures.up import Up

from .conftest import ARTIFACTS, open_replay

SCREENSHOT = ROOT / "docs" / "screenshot.png"
TIMEOUT_MS = 90_000
DAY_MS = 86_400_000


def stitched_free(api: str, at: int, ros_map) -> np.ndarray:
    """Drivable pixels of the map at `at`, from the API's chunks."""
    doc = httpx.get(f"{api}/api/v1/map", params={"at": at}, timeout=60).json()
    meta = doc["meta"]
    cw, ch = meta["CHUNK_WIDTH"], meta["CHUNK_HEIGHT"]
    canvas = np.zeros((meta["CHUNK_ROWS"] * ch, meta["CHUNK_COLS"] * cw), np.uint8)
    for c in doc["chunks"]:
        raw = httpx.get(
            f"{api}/api/v1/chunk-contents/{c['content_hash']}",
            params={"encoding": "raw"},
            timeout=60,
        ).content
        canvas[c["row"] * ch : (c["row"] + 1) * ch, c["column"] * cw : (c["column"] + 1) * cw] = (
            np.frombuffer(raw, np.uint8).reshape(ch, cw)
        )
    return drivable(ros_map.with_pixels(canvas[: ros_map.height, : ros_map.width]))


def test_first_make_up_shows_the_floor_and_a_past(tmp_path, page) -> None:
    """Fresh up: the UI shows the map file at now (but for simulator changes) and history days back;
    two days ago every robot stands on a free pixel and those that reported in the last 10 s are online."""
    ros_map = load_ros_map(MAPS / "warehouse.yaml")
    up = Up(tmp_path / "data", "--robots", "3", "--history-days", "2.1")
    api = f"http://127.0.0.1:{up.api_port}"
    try:
        # Live, now: the real floor (chunks the simulator changed aside).
        open_replay(page, api, timeout_ms=TIMEOUT_MS)
        expected = {
            f"{r}:{c}": content_hash(px).hex() for (r, c), px in slice_chunks(ros_map).items()
        }
        page.wait_for_function(
            f"() => window.__replay.engine.state.cells.size === {len(expected)}", timeout=TIMEOUT_MS
        )
        cells = page.evaluate(
            "() => [...window.__replay.engine.state.cells.values()]"
            ".map(c => [`${c.row}:${c.column}`, c.content_hash, c.robotId])"
        )
        changed = [k for k, h, who in cells if h != expected[k]]
        assert all(who.startswith("sim-") for k, h, who in cells if h != expected[k]), cells
        assert len(changed) <= 12, changed

        # The past is there: the week's timeline holds robots days back.
        now = page.evaluate("() => Date.now()")
        buckets = httpx.get(
            f"{api}/api/v1/timeline",
            params={"from": now - 7 * DAY_MS + 60_000, "to": now, "buckets": 168},
            timeout=60,
        ).json()
        active_hours = [b for b in buckets["buckets"] if b["robots_active"] > 0]
        assert len(active_hours) >= 48, len(active_hours)

        # Two days ago: the floor, its robots on free pixels and online.
        t = now - 2 * DAY_MS
        open_replay(page, api, f"?t={t}&view=-2,-837,503", timeout_ms=TIMEOUT_MS)
        robots = page.evaluate("() => window.__replay.robots()")
        assert len(robots) == 3, robots
        free = stitched_free(api, t, ros_map)
        m = meta_from_json(page.evaluate("() => window.__replay.meta"))
        for r in robots:
            col, row = metres_to_pixel(r["x"], r["y"], m)
            assert free[row, col], r
            if t - r["ts_ms"] <= 10_000:
                assert r["offline"] is False, r
        assert any(t - r["ts_ms"] <= 10_000 for r in robots)
        assert page.errors == []

        shot = page.screenshot()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "first-run-two-days-ago.png").write_bytes(shot)
        image = Image.open(io.BytesIO(shot)).convert("RGB")
        colours = len(set(image.resize((320, 200)).getdata()))
        assert colours > 50, "the screenshot shows next to nothing"
        if os.environ.get("MAPSERVICE_UPDATE_SCREENSHOTS") == "1":
            SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
            SCREENSHOT.write_bytes(shot)
    finally:
        up.stop()
