"""Operators shape the floor in Chromium, against the shared stack: with an operator token a
keep-out zone is drawn by mouse across an aisle, stored, drawn at instants after its
creation and not before; a speed zone is closed with Enter and dragged; a point of
interest is placed, renamed (an empty name is refused with the server's message), dragged
and deleted; a robot's pose inside the zone shows as a
violation on the map, in the panel's list and on the timeline. A token without the
operator scope gets no edit controls, and its direct write is refused.

Where others do not look: everything here happens now (an edit is stamped by the server's
clock), after the loaded history the other tests seek into, in an aisle band (y -12.6 to
-9.4 m) none of the live tests' robots drive through. The screenshot goes to
test-artifacts/ui/ and, with MAPSERVICE_UPDATE_SCREENSHOTS=1, to docs/ui-zones.png."""

from __future__ import annotations

import time

import httpx
import pytest

from mapservice.core.wire2019 import format_timestamp
from mapservice.runtime.secrets import with_local_api_secrets
from mapservice.settings import token_list
from tests.fixtures.mosquitto import mosquitto_pub

from .annotation_drawing import (
    TIMEOUT_MS,
    center_on_metres,
    draw_zone_by_mouse,
    drawn,
    give_token,
    screen,
    seek_and_read,
)
from .test_investigator import api, open_at, screenshot

# Across the aisle between the first two racks of the warehouse's lower half (maps/warehouse.*):
# from x -8.4 to -2.6 m the band overlaps both racks' edges.
ZONE = [(-8.4, -12.6), (-2.6, -12.6), (-2.6, -11.4), (-8.4, -11.4)]
ZONE_NAME = "ui-test aisle block"
SLOW = [(-7.8, -10.9), (-3.2, -10.9), (-3.2, -10.3), (-7.8, -10.3)]
POI_AT = (-5.5, -9.6)
VIOLATOR = "ui-zone-bot"


def operator_token(stack) -> str:
    return token_list(with_local_api_secrets(stack.settings()).api_operator_tokens)[0]


def standing(stack, at: int | None = None) -> dict[str, dict]:
    params = {"at": at} if at is not None else {}
    return {
        a["annotation"]["name"]: a
        for a in api(stack, "/api/v1/annotations", **params)["annotations"]
    }


def test_an_operator_draws_a_zone_places_and_renames_a_point(page, history_stack) -> None:
    stack = history_stack
    meta = httpx.get(f"{stack.api_url}/api/chunk-service/meta", timeout=30).json()
    assert meta["resolution"] == pytest.approx(0.03)
    open_at(page, stack, "?panels=annotations")
    page.evaluate("() => localStorage.removeItem('mapservice.apiToken')")
    assert page.locator('[data-testid="edit-panel"]').count() == 0
    give_token(page, operator_token(stack))
    page.wait_for_selector('[data-testid="edit-panel"]', timeout=TIMEOUT_MS)
    # Zoomed in on the aisle: one screen pixel is one map pixel (3 cm).
    center_on_metres(page, meta, -5.5, -11.0)

    # Esc drops a zone half drawn: nothing is stored.
    page.click('[data-testid="draw-zone"]')
    for x, y in ZONE[:2]:
        page.mouse.click(*screen(page, x, y))
    page.keyboard.press("Escape")
    assert drawn(page)["tool"] is None and page.locator('[data-testid="edit-hint"]').count() == 0
    assert ZONE_NAME not in standing(stack)

    # The zone, by mouse: four corners, a double-click on the last closes it.
    page.fill('[data-testid="zone-name"]', ZONE_NAME)
    page.select_option('[data-testid="zone-kind"]', "keep_out")
    draw_zone_by_mouse(page, ZONE)
    page.wait_for_selector('[data-testid="edit-status"]', timeout=TIMEOUT_MS)
    assert page.locator('[data-testid="annotation-error"]').count() == 0
    zone = standing(stack)[ZONE_NAME]
    doc = zone["annotation"]
    assert (doc["shape"], doc["kind"]) == ("zone", "keep_out")
    assert len(doc["polygon"]) == 4  # the double-click's repeated corner is not a vertex
    for (x, y), (sx, sy) in zip(doc["polygon"], ZONE):
        assert (x, y) == (pytest.approx(sx, abs=0.06), pytest.approx(sy, abs=0.06))
    created = zone["created_ms"]
    assert zone["created_by"].startswith("operator:")

    # Drawn as it was: not before its creation, from it on; its creation is marked on the timeline.
    assert zone["id"] not in seek_and_read(page, created - 60_000)["drawn"]["zones"]
    assert zone["id"] in seek_and_read(page, created + 1_000)["drawn"]["zones"]
    page.wait_for_selector(
        f'[data-testid="annotation-edit-mark"][data-ts="{created}"]', timeout=TIMEOUT_MS
    )
    # Back to now to edit on: an edit leaves a replay paused in the past where it is.
    page.click('[data-testid="live"]')
    page.wait_for_function("() => window.__replay.live && window.__replay.complete")

    # A speed zone next to it, closed with Enter: stored with its limit, labelled with it.
    page.fill('[data-testid="zone-name"]', "ui-test slow lane")
    page.select_option('[data-testid="zone-kind"]', "speed_limit")
    page.fill('[data-testid="zone-speed"]', "0.3")
    page.click('[data-testid="draw-zone"]')
    for x, y in SLOW:
        page.mouse.click(*screen(page, x, y))
    page.keyboard.press("Enter")
    page.wait_for_function(
        "() => (document.querySelector('[data-testid=edit-status]')?.innerText ?? '').includes('ui-test slow lane')",
        timeout=TIMEOUT_MS,
    )
    slow = standing(stack)["ui-test slow lane"]["annotation"]
    assert (slow["kind"], slow["speed_limit"], slow["speed_unit"], len(slow["polygon"])) == (
        "speed_limit",
        0.3,
        "m/s",
        4,
    )
    page.wait_for_function(
        "() => [...document.querySelectorAll('.zone-label span')].some(e => e.innerText.includes('≤ 0.3 m/s'))",
        timeout=TIMEOUT_MS,
    )

    # Selected once made: dragged 30 screen pixels (0.9 m) to the left, it is stored there.
    x0, y0 = screen(page, -6.5, -10.6)
    page.mouse.move(x0, y0)
    page.mouse.down()
    for k in range(1, 4):
        page.mouse.move(x0 - 10 * k, y0)
    page.mouse.up()
    deadline = time.monotonic() + 30
    while (
        time.monotonic() < deadline
        and standing(stack)["ui-test slow lane"]["annotation"]["polygon"] == slow["polygon"]
    ):
        time.sleep(0.3)
    dragged = standing(stack)["ui-test slow lane"]["annotation"]["polygon"]
    for (x, y), (sx, sy) in zip(dragged, slow["polygon"]):
        assert (x, y) == (pytest.approx(sx - 0.9, abs=0.06), pytest.approx(sy, abs=0.06))

    # A point of interest: placed by a click, renamed, dragged.
    page.fill('[data-testid="poi-name"]', "ui-test dock")
    page.select_option('[data-testid="poi-kind"]', "charger")
    page.click('[data-testid="place-poi"]')
    page.mouse.click(*screen(page, *POI_AT))
    page.wait_for_function(
        "() => (document.querySelector('[data-testid=edit-status]')?.innerText ?? '').includes('point ui-test dock')",
        timeout=TIMEOUT_MS,
    )
    poi = standing(stack)["ui-test dock"]
    assert poi["annotation"]["kind"] == "charger"
    assert (poi["annotation"]["x"], poi["annotation"]["y"]) == (
        pytest.approx(POI_AT[0], abs=0.06),
        pytest.approx(POI_AT[1], abs=0.06),
    )
    page.wait_for_selector(f'.poi[data-id="{poi["id"]}"]', timeout=TIMEOUT_MS)
    # Selected: the one just placed; then the zone from the list, the point again by a click on the map.
    page.wait_for_selector(
        f'[data-testid="annotation-row"][data-id="{poi["id"]}"].active', timeout=TIMEOUT_MS
    )
    page.locator(f'[data-testid="annotation-row"][data-id="{zone["id"]}"]').click()
    assert ZONE_NAME in page.inner_text('[data-testid="edit-selected"]')
    page.locator(f'.poi[data-id="{poi["id"]}"]').click()
    page.wait_for_selector(
        f'[data-testid="annotation-row"][data-id="{poi["id"]}"].active', timeout=TIMEOUT_MS
    )
    # A refusal says why, in the server's words.
    page.fill('[data-testid="rename-input"]', "")
    page.click('[data-testid="rename"]')
    page.wait_for_selector('[data-testid="annotation-error"]', timeout=TIMEOUT_MS)
    error = page.inner_text('[data-testid="annotation-error"]')
    assert "refused" in error and "422" in error and "name" in error
    page.fill('[data-testid="rename-input"]', "ui-test dock 2")
    page.click('[data-testid="rename"]')
    page.wait_for_function(
        "() => [...document.querySelectorAll('.poi-name')].some(e => e.innerText === 'ui-test dock 2')",
        timeout=TIMEOUT_MS,
    )
    renamed = standing(stack)
    assert "ui-test dock" not in renamed and renamed["ui-test dock 2"]["id"] == poi["id"]
    # Dragged 60 screen pixels (1.8 m) to the right.
    box = page.locator(f'.poi[data-id="{poi["id"]}"]').bounding_box()
    x0, y0 = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x0, y0)
    page.mouse.down()
    for k in range(1, 7):
        page.mouse.move(x0 + 10 * k, y0)
    page.mouse.up()
    deadline = time.monotonic() + 30
    while (
        time.monotonic() < deadline
        and standing(stack)["ui-test dock 2"]["annotation"]["x"] == poi["annotation"]["x"]
    ):
        time.sleep(0.3)
    moved = standing(stack)["ui-test dock 2"]["annotation"]
    assert moved["x"] == pytest.approx(POI_AT[0] + 1.8, abs=0.1) and moved["y"] == pytest.approx(
        POI_AT[1], abs=0.06
    )

    # A robot inside the zone: a violation on the map, in the list, on the timeline.
    t = int(time.time() * 1000)
    body = {
        "robotId": VIOLATOR,
        "timestamp": format_timestamp(t),
        "pose": {
            "position": {"x": -7.4, "y": -12.2, "z": 0},
            "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
        },
        "status": {"battery": {"battery_level": 0.5, "charging": False}, "loaded": False},
    }
    mosquitto_pub(stack.mqtt_port, f"iot/coordinates/{VIOLATOR}", body)
    deadline = time.monotonic() + 60
    found: list = []
    while time.monotonic() < deadline and not found:
        found = [
            v
            for v in api(stack, "/api/v1/zone-violations", **{"from": t - 1000, "to": t + 60_000})[
                "violations"
            ]
            if v["robotId"] == VIOLATOR
        ]
        time.sleep(0.5)
    assert [(v["zoneId"], v["ts_ms"]) for v in found] == [(zone["id"], t)]
    page.evaluate(
        "() => window.__replay.seek(Date.now())"
    )  # the timeline's span reaches t: marks and list read again
    page.wait_for_selector(
        f'[data-testid="violation-row"][data-robot="{VIOLATOR}"]', timeout=TIMEOUT_MS
    )
    assert ZONE_NAME in page.inner_text(f'[data-testid="violation-row"][data-robot="{VIOLATOR}"]')
    page.wait_for_selector(
        f'[data-testid="zone-violation-mark"][data-ts="{t}"]', timeout=TIMEOUT_MS
    )
    page.locator(f'[data-testid="violation-row"][data-robot="{VIOLATOR}"]').click()
    page.wait_for_function(
        f"() => window.__replay.playhead === {t} && window.__replay.complete", timeout=TIMEOUT_MS
    )
    page.wait_for_selector(f'.violation[data-robot="{VIOLATOR}"]', timeout=TIMEOUT_MS)
    assert VIOLATOR in drawn(page)["drawn"]["violations"]
    # The layer switch hides them, the address keeps it.
    assert drawn(page)["shown"] is True
    page.click('input[data-layer="annotations"]')
    page.wait_for_function(
        "() => !(new URLSearchParams(location.search).get('layers') ?? '').includes('annotations')"
    )
    assert drawn(page)["shown"] is False and page.locator(".poi").count() == 0
    page.click('input[data-layer="annotations"]')
    page.wait_for_function("() => window.__replay.annotations().shown")
    page.locator(f'[data-testid="annotation-row"][data-id="{zone["id"]}"]').click()
    # The timeline zoomed to the last minutes (a drag across its right end): the marks apart.
    strip = page.locator('[data-testid="timeline-strip"]').bounding_box()
    page.mouse.move(strip["x"] + strip["width"] * 0.93, strip["y"] + 20)
    page.mouse.down()
    page.mouse.move(strip["x"] + strip["width"] * 0.97, strip["y"] + 20)
    page.mouse.move(strip["x"] + strip["width"] - 1, strip["y"] + 20)
    page.mouse.up()
    page.wait_for_timeout(1000)
    screenshot(page, "ui-zones.png")

    # Deleted: gone from now on, still there before.
    removed_before = int(time.time() * 1000)
    page.locator(f'[data-testid="annotation-row"][data-id="{poi["id"]}"]').click()
    page.click('[data-testid="delete"]')
    # Paused before it, the point is still there; "show it" goes to the deletion.
    page.wait_for_function(
        "() => (document.querySelector('[data-testid=edit-status]')?.innerText ?? '').includes('remove ui-test dock 2')",
        timeout=TIMEOUT_MS,
    )
    page.click('[data-testid="edit-show"]')
    page.wait_for_function(
        "(id) => !document.querySelector(`.poi[data-id='${id}']`)",
        arg=poi["id"],
        timeout=TIMEOUT_MS,
    )
    assert "ui-test dock 2" not in standing(stack)
    assert "ui-test dock 2" in standing(stack, removed_before)
    assert poi["id"] in seek_and_read(page, removed_before)["drawn"]["points"]
    assert page.locator('[data-testid="annotation-error"]').count() == 0
    assert page.errors == []


def test_a_token_without_the_operator_scope_gets_no_edit_controls(page, history_stack) -> None:
    stack = history_stack
    writer = stack.api_secrets().writers[0]  # read and the 2019 writes, not shaping the floor
    open_at(page, stack, "?panels=annotations")
    give_token(page, writer)
    page.wait_for_function("() => localStorage.getItem('mapservice.apiToken') !== null")
    page.wait_for_timeout(1000)  # the scopes are asked for again
    assert drawn(page)["operator"] is False
    assert page.locator('[data-testid="edit-panel"]').count() == 0
    assert page.locator('[data-testid="draw-zone"]').count() == 0
    assert page.locator('[data-testid="annotation-panel"]').count() == 1
    body = {"shape": "poi", "name": "not allowed", "kind": "note", "x": 0, "y": 0}
    for headers, status in (({"Authorization": f"Bearer {writer}"}, 403), ({}, 401)):
        r = httpx.post(
            f"{stack.api_url}/api/v1/annotations", json=body, headers=headers, timeout=30
        )
        assert r.status_code == status and "operator" in r.json()["detail"]
    assert "not allowed" not in standing(stack)
    assert page.errors == []
