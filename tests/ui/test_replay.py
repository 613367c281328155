"""The replay UI in headless Chromium against a running service with loaded history."""

from __future__ import annotations

import io
import json
import time

import httpx
import pytest
from PIL import Image

from mapservice.bench.ui_expected import expected_at
from tests.fixtures.mosquitto import mosquitto_pub

from .conftest import ARTIFACTS, open_replay

TIMEOUT_MS = 60_000


def api(stack, path: str, **params):
    r = httpx.get(f"{stack.api_url}{path}", params=params, timeout=60)
    r.raise_for_status()
    return r.json()


def open_at(page, stack, query: str) -> None:
    open_replay(page, stack.api_url, query, timeout_ms=TIMEOUT_MS)


def expected_writes(stack, a: int, b: int) -> list[list]:
    """Every write with a < ts <= b in the order the UI applies them (time, robot, cell)."""
    rows = api(stack, "/api/v1/chunk-events", **{"from": a + 1, "to": b + 1, "limit": 100000})
    rows.sort(key=lambda r: (r["ts_ms"], r["robotId"], r["row"], r["column"]))
    return [[r["ts_ms"], r["robotId"], r["row"], r["column"]] for r in rows]


def crossed_writes(stack, page, a: int, b: int) -> list[list]:
    """The writes the page must apply (a < b) or undo (a > b) between a and b at the
    compaction it uses (every write up to 60x, the server's bucket winners above), in the
    order the UI applies them."""
    step = page.evaluate("() => window.__replay.chunkStepMs")
    _, rows = expected_at(stack.api_url, a, b, step)
    rows.sort(key=lambda r: (r["ts_ms"], r["robotId"], r["row"], r["column"]))
    return [[r["ts_ms"], r["robotId"], r["row"], r["column"]] for r in rows]


def applied_forward(page) -> list[list]:
    return page.evaluate(
        "() => window.__replay.log.filter(l => l.dir === 1).map(l => [l.ts_ms, l.robotId, l.row, l.column])"
    )


def shown_hashes(page) -> dict[str, str]:
    return page.evaluate(
        "() => Object.fromEntries([...window.__replay.engine.state.cells.values()]"
        ".map(c => [`${c.row}:${c.column}`, c.content_hash]))"
    )


def map_hashes(stack, at: int) -> dict[str, str]:
    return {
        f"{c['row']}:{c['column']}": c["content_hash"]
        for c in api(stack, "/api/v1/map", at=at)["chunks"]
    }


def play_until(page, speed: int, direction: int, until_ms: int, timeout_s: float = 90) -> int:
    """Plays until the playhead passes `until_ms`, pauses, and returns where it stopped."""
    page.evaluate(
        "([s, d]) => { window.__replay.clearLog(); window.__replay.play(s, d); }",
        [speed, direction],
    )
    cmp = ">=" if direction > 0 else "<="
    # Paused from inside the page, in the frame that passes `until_ms`: at 86400x a round
    # trip from here would play on for tens of minutes of history, up to now (live mode).
    page.wait_for_function(
        f"() => {{ const r = window.__replay; if (r.seeking || !(r.playhead {cmp} {until_ms})) return false;"
        " r.pause(); return true; }",
        polling="raf",
        timeout=timeout_s * 1000,
    )
    time.sleep(0.3)  # a frame applies what the pause left
    return page.evaluate("() => window.__replay.playhead")


def test_seek_shows_known_chunk_pixels_and_robot_positions(page, history_stack) -> None:
    """A deep link to T draws every chunk of the map at T and every robot where it was."""
    stack = history_stack
    t = stack.history.start_ms + 90 * 60_000
    open_at(page, stack, f"?t={t}&view=-1,-300,500")
    assert page.evaluate("() => window.__replay.playhead") == t
    assert shown_hashes(page) == map_hashes(stack, t)
    # The pixels of a known chunk: canvas and screen both show the stored content.
    chunk = api(stack, "/api/v1/map", at=t)["chunks"][0]
    raw = httpx.get(
        f"{stack.api_url}/api/v1/chunk-contents/{chunk['content_hash']}", params={"encoding": "raw"}
    ).content
    meta = page.evaluate("() => window.__replay.meta")
    cw, ch = meta["CHUNK_WIDTH"], meta["CHUNK_HEIGHT"]
    page.evaluate(
        "([r, c]) => window.__replay.centerOnPixel(r, c, 1)",
        [chunk["row"] * ch + ch / 2, chunk["column"] * cw + cw / 2],
    )
    page.wait_for_function("() => window.__replay.complete", timeout=TIMEOUT_MS)
    for dy, dx in ((5, 5), (50, 50), (90, 20)):
        px = page.evaluate(
            "([r, c]) => window.__replay.chunkPixel(r, c)",
            [chunk["row"] * ch + dy, chunk["column"] * cw + dx],
        )
        assert px[:3] == [raw[dy * cw + dx]] * 3
    # A screenshot pixel in a uniform patch of that chunk, centred on screen, robots hidden.
    uniform = [
        (y, x)
        for y in range(10, ch - 10, 5)
        for x in range(10, cw - 10, 5)
        if len({raw[(y + j) * cw + x + i] for j in range(-3, 4) for i in range(-3, 4)}) == 1
    ]
    assert uniform, "the known chunk has no uniform patch"
    y, x = uniform[len(uniform) // 2]
    r, c = chunk["row"] * ch + y + 0.5, chunk["column"] * cw + x + 0.5
    page.evaluate("([r, c]) => window.__replay.centerOnPixel(r, c, 1)", [r, c])
    page.wait_for_function("() => window.__replay.complete", timeout=TIMEOUT_MS)
    page.evaluate("() => document.querySelector('.leaflet-marker-pane').style.display = 'none'")
    centre = page.evaluate("([r, c]) => window.__replay.screenPointOfPixel(r, c)", [r, c])
    shot = Image.open(io.BytesIO(page.screenshot())).convert("RGB")
    value = shot.getpixel((int(centre["x"]), int(centre["y"])))
    assert all(abs(v - raw[y * cw + x]) <= 2 for v in value), (value, raw[y * cw + x])
    page.evaluate("() => document.querySelector('.leaflet-marker-pane').style.display = ''")
    # Every robot at its stored pose, drawn there in its battery colour.
    page.evaluate("() => window.__replay.fitGrid()")
    robots = {r["robotId"]: r for r in api(stack, "/api/v1/robots", at=t)["robots"]}
    shown = {r["robotId"]: r for r in page.evaluate("() => window.__replay.robots()")}
    assert set(shown) == set(robots)
    for rid, r in robots.items():
        assert shown[rid]["x"] == pytest.approx(r["position"][0], abs=1e-6)
        assert shown[rid]["y"] == pytest.approx(r["position"][1], abs=1e-6)
    page.wait_for_function("(n) => window.__replay.drawnRobots().length === n", arg=len(robots))
    drawn = {d["robotId"]: d for d in page.evaluate("() => window.__replay.drawnRobots()")}
    shot = Image.open(io.BytesIO(page.screenshot())).convert("RGB")
    battery_colours = {(44, 160, 44), (255, 159, 28), (214, 39, 40), (136, 136, 136)}
    box = page.locator('[data-testid="map"]').bounding_box()
    checked = 0
    for rid, r in robots.items():
        at = page.evaluate(
            "([x, y]) => window.__replay.screenPointOfMetres(x, y)", r["position"][:2]
        )
        assert abs(drawn[rid]["x"] - at["x"]) <= 0.5 and abs(drawn[rid]["y"] - at["y"]) <= 0.5
        if (
            box["x"] + 10 <= at["x"] < box["x"] + box["width"] - 10
            and box["y"] + 10 <= at["y"] < box["y"] + box["height"] - 10
        ):
            checked += 1
            assert shot.getpixel((round(at["x"]), round(at["y"]))) in battery_colours
    assert checked, "no robot inside the map's viewport"
    # Clicking a robot opens its details, clock-skew flag included.
    rid, d = next(
        (k, v)
        for k, v in drawn.items()
        if box["x"] + 10 <= v["x"] < box["x"] + box["width"] - 10
        and box["y"] + 10 <= v["y"] < box["y"] + box["height"] - 10
    )
    page.mouse.click(d["x"], d["y"])
    details = page.locator('[data-testid="robot-details"]')
    details.wait_for(timeout=TIMEOUT_MS)
    page.locator('[data-testid="clock-skew"]').wait_for(timeout=TIMEOUT_MS)
    assert rid in details.inner_text() and "clock skew" in details.inner_text()
    assert not page.errors


@pytest.mark.parametrize("speed", [8, 86400])
def test_play_applies_every_change_in_order(page, history_stack, speed) -> None:
    """Playing forwards applies each write between frames in order, none skipped: every
    stored write at 8x, each 20 min bucket's winners (chunk_step_ms) at 86400x."""
    stack = history_stack
    # At 86400x a frame is ~25 min of history: stop well before now (the history ends
    # 10 min before the fixture started), or the playhead hands over to live mode.
    start = stack.history.start_ms + (30 if speed == 8 else 10) * 60_000
    until = start + (60_000 if speed == 8 else 60 * 60_000)
    open_at(page, stack, f"?t={start}&speed={speed}")
    stopped = play_until(page, speed, 1, until)
    expected = crossed_writes(stack, page, start, stopped)
    if speed == 8:
        assert expected == expected_writes(stack, start, stopped)
    assert len(expected) > (10 if speed == 8 else 100)
    assert applied_forward(page) == expected
    # Paused between two bucket boundaries the page reloads the exact map at the playhead.
    page.wait_for_function(
        f"() => !window.__replay.seeking && (window.__replay.chunkStepMs === 0"
        f" || window.__replay.mapExactAt === {stopped})",
        timeout=TIMEOUT_MS,
    )
    assert shown_hashes(page) == map_hashes(stack, stopped)
    assert not page.errors


def test_play_backwards_restores_each_earlier_state(page, history_stack) -> None:
    """Playing backwards at 3600x across fetched spans undoes each minute's winning writes
    and ends on exactly the map at that T."""
    stack = history_stack
    start = stack.history.start_ms + 150 * 60_000
    open_at(page, stack, f"?t={start}&speed=3600&dir=-1")
    stopped = play_until(page, 3600, -1, start - 3_600_000)
    undone = page.evaluate("() => window.__replay.log.filter(l => l.dir === -1).length")
    assert undone == len(crossed_writes(stack, page, start, stopped)) > 0
    page.wait_for_function(
        f"() => !window.__replay.seeking && window.__replay.mapExactAt === {stopped}",
        timeout=TIMEOUT_MS,
    )
    assert shown_hashes(page) == map_hashes(stack, stopped)
    assert not page.errors


def test_deep_link_reopens_the_same_moment_speed_and_view(page, history_stack) -> None:
    """The URL a paused replay writes opens the same instant, speed and view in a new tab."""
    stack = history_stack
    t = stack.history.start_ms + 100 * 60_000 + 12_345
    open_at(page, stack, f"?t={t}&speed=60&view=0.5,-800,1200")
    page.wait_for_function("() => location.search.includes('view=')")
    link = page.url
    other = page.context.new_page()
    other.goto(link)
    other.wait_for_function("() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS)
    assert other.evaluate("() => window.__replay.playhead") == t
    assert other.locator('[data-speed="60"]').get_attribute("class") == "on"
    assert other.evaluate("() => window.__replay.view()") == {"zoom": 0.5, "lat": -800, "lng": 1200}
    assert "view=0.5%2C-800%2C1200" in other.url or "view=0.5,-800,1200" in other.url
    assert (
        other.locator('[data-testid="playhead"]')
        .inner_text()
        .startswith(time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t / 1000)))
    )
    other.screenshot(path=str(ARTIFACTS / "deep_link_reopened.png"))
    other.close()


def test_live_mode_shows_a_pose_published_with_mosquitto_pub(page, history_stack) -> None:
    """In live mode a pose sent over MQTT like a 2019 robot appears on the map."""
    stack = history_stack
    open_at(page, stack, "?live=1")
    page.wait_for_function("() => window.__replay.liveStatus.connected", timeout=TIMEOUT_MS)
    ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime())
    meta = page.evaluate("() => window.__replay.meta")
    x, y = meta["origin"][0] + 10.0, meta["origin"][1] + 10.0
    body = json.dumps(
        {
            "robotId": "ui-live",
            "timestamp": ts,
            "pose": {
                "position": {"x": x, "y": y, "z": 0},
                "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
            },
            "status": {"battery": {"battery_level": 80, "charging": False}, "loaded": True},
        }
    )
    mosquitto_pub(stack.mqtt_port, "iot/coordinates/ui-live", body)
    page.wait_for_function(
        "() => window.__replay.drawnRobots().some(r => r.robotId === 'ui-live')", timeout=TIMEOUT_MS
    )
    shown = {r["robotId"]: r for r in page.evaluate("() => window.__replay.robots()")}
    assert shown["ui-live"]["x"] == pytest.approx(x) and shown["ui-live"]["y"] == pytest.approx(y)
    page.wait_for_function(
        "() => document.querySelector('[data-testid=latency]').innerText.includes('latency')"
    )
    assert not page.errors


def test_timeline_density_click_to_seek_and_keyboard(page, history_stack) -> None:
    """Presets show the change density and where robots reported; a click seeks there;
    arrows step, L goes live."""
    stack = history_stack
    t = stack.history.start_ms + 60 * 60_000
    open_at(page, stack, f"?t={t}")
    page.locator('[data-preset="6h"]').click()
    page.wait_for_function(
        "() => document.querySelectorAll('.strip .bar').length > 10", timeout=TIMEOUT_MS
    )
    assert page.locator(".strip .active").count() > 10
    box = page.locator('[data-testid="timeline-strip"]').bounding_box()
    page.mouse.click(box["x"] + box["width"] * 0.25, box["y"] + box["height"] / 2)
    page.wait_for_function(
        f"() => window.__replay.playhead !== {t} && window.__replay.complete", timeout=TIMEOUT_MS
    )
    clicked = page.evaluate("() => window.__replay.playhead")
    now = time.time() * 1000
    assert now - 6 * 3_600_000 - 120_000 < clicked < now - 3 * 3_600_000
    page.locator('[data-testid="map"]').click(position={"x": 5, "y": 300})
    page.keyboard.press("ArrowRight")
    page.wait_for_function(
        f"() => window.__replay.playhead === {clicked + 1000} && window.__replay.complete",
        timeout=TIMEOUT_MS,
    )
    page.keyboard.press("l")
    page.wait_for_function("() => window.__replay.live", timeout=TIMEOUT_MS)
    assert not page.errors


def test_playing_into_now_hands_over_to_live(page, history_stack) -> None:
    """Playing forwards until the present switches to live mode instead of polling."""
    stack = history_stack
    start = int(time.time() * 1000) - 30_000
    open_at(page, stack, f"?t={start}&speed=8&play=1")
    page.wait_for_function("() => window.__replay.live", timeout=TIMEOUT_MS)
    page.wait_for_function("() => window.__replay.liveStatus.connected", timeout=TIMEOUT_MS)
    assert not page.errors
