"""The heatmap layer in Chromium, against the running service over the loaded history: the
side bar's switch lays the timeline's span's heatmap over the floor (its picture the API's
PNG of the cells' box, where its summary header says, in the ramp's colours), the legend says
the kind, the span and the largest value with its unit and draws a scale bar of the view;
the kind and the cell size read it again, and the address keeps them all and reopens them.
A screenshot (1280x800) goes to test-artifacts/ui/ and, with MAPSERVICE_UPDATE_SCREENSHOTS=1,
to docs/ui-heatmap.png."""

from __future__ import annotations

import io
import math
import time

import httpx
import numpy as np
import pytest
from PIL import Image

from mapservice.core.heatmap_render import ALPHA, ramp

from .test_investigator import TIMEOUT_MS, open_at, screenshot

OVER_THE_HEATMAP = ("names", "battery", "paths", "conflicts", "annotations")


def heatmap_state(page) -> dict:
    return page.evaluate("() => window.__replay.heatmap()")


def wait_heatmap(page, kind: str, cell: float) -> dict:
    """The page's heatmap once a read of `kind` and `cell` is drawn on the map."""
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while True:
        s = heatmap_state(page)
        g = s["grid"]
        done = g and g["kind"] == kind and g["cell_m"] == cell and not s["loading"]
        if done and (s["drawn"] or g["box"] is None):
            return s
        assert not s["error"], s["error"]
        assert time.monotonic() < deadline, (
            s,
            page.errors,
            page.evaluate(
                "() => [document.querySelectorAll('.leaflet-heatmap-pane img').length,"
                " !!window.__replay.engine.meta, location.search,"
                " JSON.stringify(window.__replay.heatmap().grid?.box)]"
            ),
        )
        time.sleep(0.2)


def settled_shot(page) -> np.ndarray:
    """The page's picture once the map holds still: two screenshots a frame or two apart that
    are equal (a pan, zoom or fade in progress, slow on a loaded machine, moves pixels)."""
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    last = None
    while True:
        shot = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"))
        if last is not None and np.array_equal(shot, last):
            return shot
        assert time.monotonic() < deadline, "the page never held still"
        last = shot
        page.wait_for_timeout(150)


def assert_same_summary(a: dict, b: dict) -> None:
    """Two reads' summaries of one span: equal, the float sums to their last bits (ClickHouse
    sums a cell's speeds in whatever order its threads meet them)."""
    floats = ("max", "total")
    assert {k: v for k, v in a.items() if k not in floats} == {
        k: v for k, v in b.items() if k not in floats
    }
    assert [a[k] for k in floats] == pytest.approx([b[k] for k in floats], rel=1e-9)


def cell_pixels(page, grid: dict) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """For each cell in the map's view, the screen pixels (rows, columns) inside it, 2 px in
    from its edges, that no robot's marker (a 16 px disc) nor the legend covers, and its value."""
    robots = page.evaluate("() => window.__replay.drawnRobots()")
    legend = page.eval_on_selector(
        '[data-testid="heatmap-legend"]',
        "e => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; }",
    )
    size = grid["cell_m"]
    corners = [(i * size, j * size, (i + 1) * size, (j + 1) * size) for i, j, _ in grid["cells"]]
    boxes = page.evaluate(
        "(cs) => cs.map(([x0, y0, x1, y1]) => [window.__replay.screenPointOfMetres(x0, y0),"
        " window.__replay.screenPointOfMetres(x1, y1)])",
        corners,
    )
    cells = []
    for (_, _, value), (a, b) in zip(grid["cells"], boxes, strict=True):
        left, right = sorted((a["x"], b["x"]))
        top, bottom = sorted((a["y"], b["y"]))
        ys, xs = np.mgrid[
            max(math.ceil(top) + 2, 40) : min(math.floor(bottom) - 2, 700),
            max(math.ceil(left) + 2, 0) : min(math.floor(right) - 2, 1000),
        ]
        keep = np.ones(xs.shape, dtype=bool)
        for r in robots:
            keep &= np.hypot(xs - r["x"], ys - r["y"]) > 16
        keep &= ~(
            (xs >= legend[0] - 5)
            & (xs <= legend[2] + 5)
            & (ys >= legend[1] - 5)
            & (ys <= legend[3] + 5)
        )
        if keep.any():
            cells.append((ys[keep], xs[keep], value))
    return cells


def wait_address(page, key: str, value: str | None) -> None:
    """Waits until the page's address has `key` = `value` (None: has no `key`); the page
    writes its address at a later frame than it draws."""
    page.wait_for_function(
        "([k, v]) => new URLSearchParams(location.search).get(k) === v",
        arg=[key, value],
        timeout=TIMEOUT_MS,
    )


def test_the_heatmap_layer_shows_the_spans_heatmap_with_its_legend_and_scale(
    page, history_stack
) -> None:
    stack = history_stack
    end = stack.history.end_ms
    span = (end - 2 * 3_600_000, end)
    open_at(page, stack, f"?t={end - 1_800_000}&span={span[0]},{span[1]}")
    wait_address(page, "heat", None)
    page.check('[data-testid="heatmap-on"]')
    page.select_option('[data-testid="heatmap-cell"]', "2")
    s = wait_heatmap(page, "occupancy", 2)
    grid = s["grid"]
    wait_address(page, "heat", "occupancy,2")
    # The page's grid (the PNG's summary header) is the API's JSON for the same span, but
    # the cells, which the page never asks for.
    params = {"kind": "occupancy", "from": grid["from_ms"], "to": grid["to_ms"], "cell": 2}
    served = httpx.get(f"{stack.api_url}/api/v1/heatmap", params=params, timeout=60).json()
    assert_same_summary({k: v for k, v in served.items() if k != "cells"}, grid)
    assert grid["max"] > 0
    grid = {**grid, "cells": served["cells"]}
    # Every robot-second of the loaded robots' two hours (a pose a second) is on the map.
    assert grid["total"] >= stack.history.robots * 7000
    # The picture over the floor: one pixel a cell of the cells' box.
    size = page.evaluate(
        "() => { const i = document.querySelector('.leaflet-heatmap-pane img.heatmap');"
        " return i && i.complete ? [i.naturalWidth, i.naturalHeight] : null; }"
    )
    assert size == [grid["box"]["columns"], grid["box"]["rows"]]
    # Over the floor, translucent: inside every cell (away from the robots' markers and the
    # legend), the page shows the floor as it is without the layer, blended with the cell's
    # colour on the ramp at the picture's alpha. The robots' labels, batteries and paths, the
    # conflicts' boxes and the zones are hidden for it: the robots stand on their fullest
    # cells, and what other tests of the shared stack drew is not this test's.
    for layer in OVER_THE_HEATMAP:
        page.uncheck(f'input[data-layer="{layer}"]')
    with_layer = settled_shot(page)
    cells = cell_pixels(page, grid)
    assert len(cells) >= len(grid["cells"]) // 2, (len(cells), len(grid["cells"]))
    page.uncheck('[data-testid="heatmap-on"]')
    page.wait_for_function("() => !document.querySelector('.leaflet-heatmap-pane img.heatmap')")
    floor = settled_shot(page)
    page.check('[data-testid="heatmap-on"]')
    wait_heatmap(page, "occupancy", 2)
    colours = ramp(np.array([value / grid["max"] for _, _, value in cells]))
    wrong = []
    for (ys, xs, value), colour in zip(cells, colours, strict=True):
        blended = (colour.astype(float) * ALPHA + floor[ys, xs].astype(float) * (255 - ALPHA)) / 255
        off = np.abs(with_layer[ys, xs] - blended).max(axis=1) > 4
        if off.mean() > 0.02:
            at = int(np.argmax(off))
            wrong.append(
                (
                    value,
                    int(xs[at]),
                    int(ys[at]),
                    with_layer[ys[at], xs[at]].tolist(),
                    blended[at].round().tolist(),
                    f"{off.mean():.0%}",
                )
            )
    assert not wrong, (len(cells), wrong)
    for layer in OVER_THE_HEATMAP:
        page.check(f'input[data-layer="{layer}"]')
    # The legend: kind, cells, the largest value in its unit, a scale bar of the view.
    legend = page.inner_text('[data-testid="heatmap-legend"]')
    assert "occupancy" in legend and "2 m cells" in legend and "(robot time)" in legend
    bar = page.eval_on_selector('[data-testid="heatmap-scale"] .bar', "b => b.offsetWidth")
    assert 20 <= bar <= 122
    label = page.inner_text('[data-testid="heatmap-scale"]').strip()
    metres = float(label.split()[0]) * (1000 if label.endswith("km") else 1)
    if label.endswith("cm"):
        metres = float(label.split()[0]) / 100
    a = page.evaluate("() => window.__replay.screenPointOfMetres(0, 0)")
    b = page.evaluate("([x]) => window.__replay.screenPointOfMetres(x, 0)", [metres])
    assert abs((b["x"] - a["x"]) - bar) <= 3  # the bar is as long as its label on the map
    screenshot(page, "ui-heatmap.png")
    # Another kind is read and drawn; the address follows.
    page.select_option('[data-testid="heatmap-kind"]', "speed")
    s = wait_heatmap(page, "speed", 2)
    wait_address(page, "heat", "speed,2")
    assert s["grid"]["unit"] == "m/s" and s["drawn"]
    # The address reopens it.
    url = page.url
    page.goto("about:blank")
    page.goto(url)
    page.wait_for_function("() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS)
    assert_same_summary(wait_heatmap(page, "speed", 2)["grid"], s["grid"])
    assert page.input_value('[data-testid="heatmap-kind"]') == "speed"
    assert page.input_value('[data-testid="heatmap-cell"]') == "2"
    assert page.is_checked('[data-testid="heatmap-on"]')
    # Off: no picture, no legend, nothing in the address.
    page.uncheck('[data-testid="heatmap-on"]')
    wait_address(page, "heat", None)
    assert page.query_selector(".leaflet-heatmap-pane img.heatmap") is None
    assert page.query_selector('[data-testid="heatmap-legend"]') is None
    assert not page.errors
