"""Robots respect the operators' zones, end to end on a fresh `mapservice up` (its own
simulated robots, the real embedded stack): an operator draws a keep-out zone by mouse in
the replay UI (Chromium) across an aisle a robot is about to drive, and a speed zone is
created through the API. From the zone's creation plus the advertisement's latency, over
two minutes of stored poses none lies inside the keep-out zone, no zone violation is
recorded and no planned path crosses it, and the stored speed inside the speed zone is the
limit's. Back in the browser, a seek to before the zone's creation does not draw it, a seek
after does; the screenshot goes to test-artifacts/ui/up-keep-out-zone.png.

Bounded: `up` takes a minute or so, then the robots drive until a path offers an aisle to
close (seconds, at most 30), then the two minutes."""

from __future__ import annotations

import math
import time

import httpx
import pytest

from mapservice.adapters.costmap_filters import grid_of
from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.core.annotations import Zone
from mapservice.core.zone_masks import pixel_of, zone_pixels
from mapservice.runtime.secrets import OPERATOR_TOKEN_FILE, stored_secret
from tests.fixtures.paths import MAPS
from tests.fixtures.up import Up
from tests.ui.annotation_drawing import (
    TIMEOUT_MS,
    center_on_metres,
    draw_zone_by_mouse,
    give_token,
    seek_and_read,
)
from tests.ui.conftest import ARTIFACTS, DIST, module_browser, page  # noqa: F401  (fixtures)

pytestmark = [pytest.mark.integration, pytest.mark.long]

WATCH_S = 120  # the acceptance's two minutes of poses
GRACE_S = 10  # the zone reaches the robots (store, advertisement, API read) and they act
SPEED_PERCENT = 25
KEEP_OUT_NAME = "aisle closed"


@pytest.fixture(scope="module")
def browser(module_browser):
    """This module's browser ends with the module (see tests/ui/conftest.playwright_browser)."""
    return module_browser


def box(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


def poses(up: Up, from_ms: int, to_ms: int) -> list[dict]:
    rows = up.api("/api/v1/poses", **{"from": from_ms, "to": to_ms, "limit": 100_000}).json()
    return sorted(rows, key=lambda p: (p["robotId"], p["ts_ms"]))


def aisle_crossing(latest: list[dict]) -> tuple[list[list[float]], str] | None:
    """A band across the aisle some robot is about to drive (1 m along its path, 4 m across
    it) with no robot within 3 m of it now: (the polygon, that robot), or None."""
    where = [(p["position"][0], p["position"][1]) for p in latest]
    for p in latest:
        path = p["path"] or []
        for (x0, y0), (x1, y1) in zip(path[1:], path[2:]):
            mx, my = (x0 + x1) / 2, (y0 + y1) / 2
            if math.dist((x0, y0), (x1, y1)) < 1.0 or any(
                math.dist((mx, my), w) < 3.0 for w in where
            ):
                continue
            if abs(x1 - x0) >= abs(y1 - y0):  # the aisle runs along x: the band spans y
                return box(mx - 0.5, my - 2.0, mx + 0.5, my + 2.0), p["robotId"]
            return box(mx - 2.0, my - 0.5, mx + 2.0, my + 0.5), p["robotId"]
    return None


def test_robots_keep_out_of_a_zone_drawn_across_their_aisle_and_slow_in_a_speed_zone(
    tmp_path, page
):
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    data = tmp_path / "data"
    up = Up(data, "--robots", "5", "--history-days", "0")
    try:
        token = stored_secret(data, OPERATOR_TOKEN_FILE)
        assert token
        # The robots drive and their poses are stored.
        deadline, latest = time.monotonic() + 90, []
        while time.monotonic() < deadline:
            now = int(time.time() * 1000)
            recent = poses(up, now - 5_000, now)
            latest = list({p["robotId"]: p for p in recent}.values())
            if len(latest) == 5 and sum(bool(p["path"]) for p in latest) >= 3:
                break
            time.sleep(2)
        assert len(latest) == 5, f"no poses of 5 robots stored: {latest}"
        # While a shift gets under way (robots on the aisles between stations), the operator
        # opens the replay UI with the operator token, ready to draw a keep-out zone.
        page.goto(f"http://127.0.0.1:{up.api_port}/?panels=annotations")
        page.wait_for_function(
            "() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS
        )
        give_token(page, token)
        page.wait_for_selector('[data-testid="edit-panel"]', timeout=TIMEOUT_MS)
        page.fill('[data-testid="zone-name"]', KEEP_OUT_NAME)
        page.select_option('[data-testid="zone-kind"]', "keep_out")
        meta = up.api("/api/chunk-service/meta").json()
        # The band is looked for as the shift gets under way, until some robot's path
        # offers a straight stretch away from the others (rather than after a fixed wait).
        deadline = time.monotonic() + 30
        while True:
            now = int(time.time() * 1000)
            latest = list({p["robotId"]: p for p in poses(up, now - 3_000, now)}.values())
            if (found := aisle_crossing(latest)) is not None:
                break
            assert time.monotonic() < deadline, (
                f"no robot drives a straight stretch away from the others: {latest}"
            )
            time.sleep(1)
        band, crossing = found
        (x0, y0), (x1, y1) = band[0], band[2]
        center_on_metres(page, meta, (x0 + x1) / 2, (y0 + y1) / 2)
        draw_zone_by_mouse(page, [(x, y) for x, y in band])
        page.wait_for_selector('[data-testid="edit-status"]', timeout=TIMEOUT_MS)
        assert page.locator('[data-testid="annotation-error"]').count() == 0
        standing = {
            a["annotation"]["name"]: a for a in up.api("/api/v1/annotations").json()["annotations"]
        }
        drawn_zone = standing[KEEP_OUT_NAME]
        assert drawn_zone["created_by"].startswith("operator:")
        assert drawn_zone["annotation"]["kind"] == "keep_out"
        keep_out = drawn_zone["annotation"]["polygon"]  # as stored: the mouse's corners
        assert len(keep_out) == 4
        for (x, y), (bx, by) in zip(keep_out, band):
            assert (x, y) == (pytest.approx(bx, abs=0.06), pytest.approx(by, abs=0.06))

        ros_map = load_ros_map(MAPS / "warehouse.yaml")
        grid = grid_of(meta_for(ros_map))
        assert grid is not None
        # A speed zone over the map's western half: robots cross in and out of it all shift.
        x_mid = grid.origin_x + grid.width * grid.resolution / 2
        speed = box(
            grid.origin_x - 1,
            grid.origin_y - 1,
            x_mid,
            grid.origin_y + grid.height * grid.resolution + 1,
        )
        auth = {"Authorization": f"Bearer {token}"}
        url = f"http://127.0.0.1:{up.api_port}/api/v1/annotations"
        r = httpx.post(
            url,
            json={
                "shape": "zone",
                "name": "slow",
                "kind": "speed_limit",
                "polygon": speed,
                "speed_limit": SPEED_PERCENT,
                "speed_unit": "percent",
            },
            headers=auth,
            timeout=30,
        )
        assert r.status_code == 201, r.text
        t0 = max(drawn_zone["created_ms"], r.json()["created_ms"])
        start, end = t0 + GRACE_S * 1000, t0 + (GRACE_S + WATCH_S) * 1000
        while time.time() * 1000 < end:
            time.sleep(min(5.0, max(0.1, end / 1000 - time.time())))
            assert up.proc.poll() is None, up.output[-3000:]
        # The watch's last poses stored: every robot has one stored from its end on (they
        # report every second), rather than a fixed few seconds waited.
        deadline = time.monotonic() + 30
        while len({p["robotId"] for p in poses(up, end, end + 10_000)}) < 5:
            assert time.monotonic() < deadline, "the poses after the watch were not stored"
            assert up.proc.poll() is None, up.output[-3000:]
            time.sleep(0.5)

        watched = poses(up, start, end)
        robots = {p["robotId"] for p in watched}
        assert len(robots) == 5 and len(watched) >= 5 * WATCH_S * 0.8, len(watched)

        zone_keep_out = Zone(name="k", kind="keep_out", polygon=tuple(map(tuple, keep_out)))
        inside = zone_pixels(grid, zone_keep_out)
        violating = [
            p
            for p in watched
            if (px := pixel_of(grid, p["position"][0], p["position"][1])) and inside[px]
        ]
        assert violating == [], (
            f"{len(violating)} stored poses inside the keep-out zone: {violating[:3]}"
        )
        violations = up.api("/api/v1/zone-violations", **{"from": start, "to": end}).json()
        assert violations["violations"] == [], violations
        # Nor do the robots plan through it any more; and they kept working.
        for p in watched:
            for x, y in p["path"] or []:
                px = pixel_of(grid, x, y)
                assert px is None or not inside[px], f"{p['robotId']} plans through the zone"
        moved = sum(
            math.dist(a["position"][:2], b["position"][:2]) > 0.1
            for a, b in zip(watched, watched[1:])
            if a["robotId"] == b["robotId"]
        )
        assert moved > WATCH_S, f"the robots hardly moved ({moved} steps)"

        # The speed zone: between two poses a second apart, starting inside it, a robot
        # drives at most the limit; outside it, at its top speed (1 m/s) too.
        slow_zone = Zone(
            name="s",
            kind="speed_limit",
            polygon=tuple(map(tuple, speed)),
            speed_limit=SPEED_PERCENT,
            speed_unit="percent",
        )
        slow = zone_pixels(grid, slow_zone)
        inside_moves, fast_outside = [], 0
        for a, b in zip(watched, watched[1:]):
            dt = (b["ts_ms"] - a["ts_ms"]) / 1000
            if a["robotId"] != b["robotId"] or not 0.5 <= dt <= 1.5:
                continue
            d = math.dist(a["position"][:2], b["position"][:2])
            px = pixel_of(grid, a["position"][0], a["position"][1])
            if abs(a["position"][0] - x_mid) < 0.1:
                continue  # on the zone's edge: a millimetre of rounding decides which side
            if px is not None and slow[px]:
                inside_moves.append(d / dt)
            elif d / dt > 0.8:
                fast_outside += 1
        assert inside_moves and max(inside_moves) <= SPEED_PERCENT / 100 + 0.02, inside_moves
        assert sum(v > 0.15 for v in inside_moves) >= 5, "no robot drove inside the speed zone"
        assert fast_outside >= 5
        sim_log = (data / "logs" / "sim.log").read_text()
        assert "robots take on the operators' zones" in sim_log, sim_log[-3000:]

        # Replayed as it was: not drawn before its creation, drawn after it.
        created, zone_id = drawn_zone["created_ms"], drawn_zone["id"]
        assert zone_id not in seek_and_read(page, created - 10_000)["drawn"]["zones"]
        assert zone_id in seek_and_read(page, created + 1_000)["drawn"]["zones"]
        assert zone_id in seek_and_read(page, end)["drawn"]["zones"]
        assert page.errors == []
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "up-keep-out-zone.png"))
        print(
            f"zone across the aisle of {crossing}; {len(watched)} poses watched, "
            f"{len(inside_moves)} moves in the speed zone"
        )
    finally:
        up.stop()
