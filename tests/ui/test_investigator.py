"""The investigator's tasks in Chromium, against a running service with loaded history: the
last change in an area drawn on the map (checked against the stored history), the fleet
list with battery in %, and a shared address that reopens layers, selection and panels.
Screenshots of the panels go to test-artifacts/ui/ and, with
MAPSERVICE_UPDATE_SCREENSHOTS=1, to docs/ (the README's UI section shows them)."""

from __future__ import annotations

import math
import os
import re

import httpx

from tests.fixtures.paths import ROOT

from .conftest import ARTIFACTS, open_replay

TIMEOUT_MS = 60_000
DOCS = ROOT / "docs"


def api(stack, path: str, **params):
    r = httpx.get(f"{stack.api_url}{path}", params=params, timeout=60)
    r.raise_for_status()
    return r.json()


def loaded_robots(stack, at: int) -> list[str]:
    """The robots at `at` that the loaded history drove, sorted. Other tests on the shared
    stack add robots of their own (controllers', VDA 5050 vehicles, conflict writers) whose
    names may sort first and which need not move at all."""
    loaded = {f"robot-{i:04d}" for i in range(stack.history.robots)}
    return sorted(
        r["robotId"]
        for r in api(stack, "/api/v1/robots", at=at)["robots"]
        if r["robotId"] in loaded
    )


def open_at(page, stack, query: str) -> None:
    open_replay(page, stack.api_url, query, timeout_ms=TIMEOUT_MS)


def screenshot(page, name: str) -> None:
    shot = page.screenshot()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / name).write_bytes(shot)
    if os.environ.get("MAPSERVICE_UPDATE_SCREENSHOTS") == "1":
        DOCS.mkdir(parents=True, exist_ok=True)
        (DOCS / name).write_bytes(shot)


def floor_changes(stack, span: tuple[int, int], box: dict) -> list[dict]:
    """From the stored writes: every write in the span and box that changed its chunk's
    content (the chunk's previous write by time, then robot, held other pixels), newest
    first. Uploads play no part: the loaded history has none."""
    writes = api(
        stack,
        "/api/v1/chunk-events",
        **{"from": stack.history.start_ms, "to": span[1], "limit": 100_000},
    )
    writes.sort(key=lambda w: (w["ts_ms"], w["robotId"]))
    before: dict[tuple[int, int], str] = {}
    changes = []
    for w in writes:
        k = (w["row"], w["column"])
        if (
            span[0] <= w["ts_ms"]
            and box["rowMin"] <= w["row"] <= box["rowMax"]
            and box["colMin"] <= w["column"] <= box["colMax"]
            and before.get(k) != w["content_hash"]
        ):
            changes.append(w)
        before[k] = w["content_hash"]
    return sorted(
        changes, key=lambda w: (w["ts_ms"], w["row"], w["column"], w["robotId"]), reverse=True
    )


def rows_shown(page) -> list[dict]:
    return page.evaluate(
        "() => [...document.querySelectorAll('[data-testid=change-row]')].map(e => ({kind: e.dataset.kind,"
        " ts: +e.dataset.ts, robot: e.dataset.robot, row: +e.dataset.row, col: +e.dataset.col, text: e.innerText}))"
    )


def test_last_change_in_a_drawn_area_with_its_robot_and_time(page, history_stack) -> None:
    """Open the change feed, drag a rectangle over part of the floor: the list's first line
    is the last change there, with the robot and time the history holds; clicking it shows
    the map just after it with the chunk outlined; Shift+← goes to the change before."""
    stack = history_stack
    t = stack.history.end_ms - 20 * 60_000
    open_at(page, stack, f"?t={t}&panels=changes")
    meta = page.evaluate("() => window.__replay.meta")
    page.evaluate("() => window.__replay.fitGrid()")
    cw, ch = meta["CHUNK_WIDTH"], meta["CHUNK_HEIGHT"]
    # Drag from the middle of chunk (1, 1) to the middle of chunk (2, 3).
    a = page.evaluate("([r, c]) => window.__replay.screenPointOfPixel(r, c)", [1.5 * ch, 1.5 * cw])
    b = page.evaluate("([r, c]) => window.__replay.screenPointOfPixel(r, c)", [2.5 * ch, 3.5 * cw])
    page.click('[data-testid="draw-area"]')
    page.mouse.move(a["x"], a["y"])
    page.mouse.down()
    page.mouse.move((a["x"] + b["x"]) / 2, (a["y"] + b["y"]) / 2, steps=4)
    page.mouse.move(b["x"], b["y"], steps=4)
    page.mouse.up()
    page.wait_for_selector('[data-testid="change-area"]')
    assert page.inner_text('[data-testid="change-area"]') == "area: chunk rows 1–2, columns 1–3"
    page.wait_for_function("() => new URLSearchParams(location.search).get('area') === '1,2,1,3'")
    box = {"rowMin": 1, "rowMax": 2, "colMin": 1, "colMax": 3}
    page.wait_for_function(
        "() => !document.querySelector('[data-testid=change-count]').innerText.includes('loading')"
        " && document.querySelectorAll('[data-testid=change-row]').length > 0",
        timeout=TIMEOUT_MS,
    )
    assert all(1 <= r["row"] <= 2 and 1 <= r["col"] <= 3 for r in rows_shown(page))
    span = tuple(page.evaluate("() => window.__replay.span()"))
    expected = floor_changes(stack, (int(span[0]), int(span[1]) + 1), box)
    assert len(expected) >= 2, "the span holds too few changes in the area to test"
    shown = rows_shown(page)
    last = expected[0]
    assert (shown[0]["ts"], shown[0]["robot"], shown[0]["row"], shown[0]["col"]) == (
        last["ts_ms"],
        last["robotId"],
        last["row"],
        last["column"],
    )
    # What the worker reads: the time (UTC) and the robot on the line itself.
    assert last["timestamp"][:19].replace("T", " ") in shown[0]["text"]
    assert (
        last["robotId"] in shown[0]["text"]
        and f"row {last['row']}, column {last['column']}" in shown[0]["text"]
    )
    assert [(s["ts"], s["row"], s["col"]) for s in shown[:10]] == [
        (e["ts_ms"], e["row"], e["column"]) for e in expected[:10]
    ]

    # Click: just after the change, its content on the map, its chunk outlined.
    page.locator('[data-testid="change-row"]').first.click()
    page.wait_for_function(
        f"() => window.__replay.playhead === {last['ts_ms'] + 1} && window.__replay.complete",
        timeout=TIMEOUT_MS,
    )
    assert (
        page.evaluate(
            "([r, c]) => window.__replay.cell(r, c).content_hash", [last["row"], last["column"]]
        )
        == last["content_hash"]
    )
    top, left = last["row"] * ch, last["column"] * cw
    assert page.evaluate("() => window.__replay.outlined()") == [[top, left], [top + ch, left + cw]]
    screenshot(page, "ui-change-feed.png")
    # Shift+←: the change before it.
    page.locator('[data-testid="map"]').click(position={"x": 5, "y": 5})
    page.keyboard.press("Shift+ArrowLeft")
    page.wait_for_function(
        f"() => window.__replay.playhead === {expected[1]['ts_ms'] + 1}", timeout=TIMEOUT_MS
    )
    assert page.errors == []


def test_fleet_panel_lists_every_robot_with_battery_percent(page, history_stack) -> None:
    """The fleet panel lists each robot with its battery in % as stored at the playhead;
    the search narrows it; a click selects and follows the robot."""
    stack = history_stack
    t = stack.history.end_ms - 30 * 60_000
    open_at(page, stack, f"?t={t}&panels=fleet")
    robots = {r["robotId"]: r for r in api(stack, "/api/v1/robots", at=t)["robots"]}
    page.wait_for_function(
        f"() => document.querySelectorAll('[data-testid=fleet-row]').length === {len(robots)}",
        timeout=TIMEOUT_MS,
    )
    page.wait_for_function(
        "() => [...document.querySelectorAll('[data-testid=fleet-speed]')]"
        ".every(e => e.innerText.endsWith('m/s'))",
        timeout=TIMEOUT_MS,
    )
    rows = page.evaluate(
        "() => [...document.querySelectorAll('[data-testid=fleet-row]')].map(e => [e.dataset.robot,"
        " e.querySelector('[data-testid=fleet-battery]').innerText,"
        " e.querySelector('[data-testid=fleet-speed]').innerText, e.innerText])"
    )
    assert [r[0] for r in rows] == sorted(robots)
    poses = api(stack, "/api/v1/poses", **{"from": t - 10_000, "to": t + 1})
    for rid, battery, speed, text in rows:
        level = robots[rid]["battery_level"]
        # Rounded half up, as the page does (Python's round() goes to even).
        pct = math.floor((level * 100 if level <= 1 else level * 20 if level <= 5 else level) + 0.5)
        assert battery == f"{pct} %", (rid, battery, level)
        a, b = [p for p in poses if p["robotId"] == rid][-2:]
        metres = (
            (b["position"][0] - a["position"][0]) ** 2 + (b["position"][1] - a["position"][1]) ** 2
        ) ** 0.5
        assert speed == f"{metres / ((b['ts_ms'] - a['ts_ms']) / 1000):.2f} m/s", (rid, speed)
        assert ("offline" if robots[rid]["online"] is False else "online") in text
    screenshot(page, "ui-fleet.png")
    target = sorted(robots)[-1]
    page.fill('[data-testid="fleet-search"]', target[-3:])
    page.wait_for_function(
        "() => document.querySelectorAll('[data-testid=fleet-row]').length === 1"
    )
    page.click(f'[data-testid="fleet-row"][data-robot="{target}"]')
    page.wait_for_function(f"() => window.__replay.selected() === '{target}'")
    assert page.inner_text('[data-testid="robot-details"] h3') == target
    assert re.search(r"battery: \d+ %", page.inner_text('[data-testid="details-battery"]'))
    page.wait_for_function(
        f"() => new URLSearchParams(location.search).get('follow') === '{target}'"
    )
    assert page.errors == []


def test_a_shared_address_reopens_layers_selection_and_panels(page, browser, history_stack) -> None:
    """Change layers, select a robot, open both panels; the address opened in another
    browser page shows the same. After a click on a layer, space still plays and pauses;
    the time box takes the address's own time format."""
    stack = history_stack
    t = stack.history.end_ms - 40 * 60_000
    open_at(page, stack, f"?t={t}")
    page.click('input[data-layer="names"]')
    page.click('input[data-layer="borders"]')
    page.click('input[data-layer="annotations"]')  # on by default: the address says it is off
    page.keyboard.press(" ")
    page.wait_for_function("() => window.__replay.playing()")
    assert page.is_checked('input[data-layer="borders"]')  # space did not toggle it back
    page.keyboard.press(" ")
    page.wait_for_function("() => !window.__replay.playing()")
    robot = loaded_robots(stack, t)[0]
    page.click('[data-testid="panel-fleet"]')
    page.click('[data-testid="panel-changes"]')
    page.click(f'[data-testid="fleet-row"][data-robot="{robot}"]')
    page.wait_for_function(f"() => new URLSearchParams(location.search).get('sel') === '{robot}'")
    # The time box, with the address's own format.
    iso = page.evaluate("() => new URLSearchParams(location.search).get('t')")
    page.fill('[data-testid="picker"]', "2026-11-24T14:00:00+01:00")
    page.press('[data-testid="picker"]', "Enter")
    assert "2026-11-24T14:00:00Z" in page.inner_text('[data-testid="notice"]')
    page.fill('[data-testid="picker"]', iso)
    page.press('[data-testid="picker"]', "Enter")
    page.wait_for_function("() => window.__replay.complete")
    shared = page.url
    q = dict(httpx.QueryParams(shared.split("?", 1)[1]))
    assert q["layers"] == "battery,paths,borders,conflicts" and q["panels"] == "changes,fleet"

    other = browser.new_context(viewport={"width": 1280, "height": 800}).new_page()
    try:
        other.goto(shared)
        other.wait_for_function(
            "() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS
        )
        layers = other.evaluate(
            "() => Object.fromEntries([...document.querySelectorAll('input[data-layer]')]"
            ".map(e => [e.dataset.layer, e.checked]))"
        )
        assert layers == {
            "names": False,
            "battery": True,
            "paths": True,
            "borders": True,
            "info": False,
            "conflicts": True,
            "annotations": False,
        }
        assert other.evaluate("() => window.__replay.selected()") == robot
        assert other.inner_text('[data-testid="robot-details"] h3') == robot
        assert other.is_visible('[data-testid="fleet-panel"]') and other.is_visible(
            '[data-testid="change-feed"]'
        )
        assert other.evaluate("() => window.__replay.playhead") == page.evaluate(
            "() => window.__replay.playhead"
        )
        screenshot(other, "ui-shared-view.png")
    finally:
        other.context.close()
    assert page.errors == []
