"""The heatmap layer in Chromium, against the running service over the loaded history: the
side bar's switch lays the timeline's span's heatmap over the floor (its picture the API's
PNG of the cells' box, where the API's JSON says, in the ramp's colours), the legend says
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
from PIL import Image

from mapservice.core.heatmap_render import ALPHA, ramp

from .test_investigator import TIMEOUT_MS, open_at, screenshot


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


def pixel(page, x: float, y: float) -> tuple[int, int, int]:
    shot = Image.open(io.BytesIO(page.screenshot())).convert("RGB")
    return shot.getpixel((round(x), round(y)))


def visible_cell(page, grid: dict) -> tuple[float, float, float]:
    """The screen point of the centre of the fullest cell that no robot's marker nor the
    legend covers, and its value."""
    robots = page.evaluate("() => window.__replay.drawnRobots()")
    legend = page.eval_on_selector(
        '[data-testid="heatmap-legend"]',
        "e => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; }",
    )
    size = grid["cell_m"]
    for i, j, value in sorted(grid["cells"], key=lambda c: -c[2]):
        at = page.evaluate(
            "([x, y]) => window.__replay.screenPointOfMetres(x, y)",
            [(i + 0.5) * size, (j + 0.5) * size],
        )
        x, y = at["x"], at["y"]
        clear = all(math.dist((x, y), (r["x"], r["y"])) > 30 for r in robots)
        under_legend = legend[0] - 5 <= x <= legend[2] + 5 and legend[1] - 5 <= y <= legend[3] + 5
        if clear and not under_legend and 0 < x < 1000 and 40 < y < 700:
            return x, y, value
    raise AssertionError("every cell is under a robot or the legend")


def address(page) -> dict[str, str]:
    page.wait_for_timeout(100)  # the page writes its address at its next frame
    return dict(page.evaluate("() => [...new URLSearchParams(location.search).entries()]"))


def test_the_heatmap_layer_shows_the_spans_heatmap_with_its_legend_and_scale(
    page, history_stack
) -> None:
    stack = history_stack
    end = stack.history.end_ms
    span = (end - 2 * 3_600_000, end)
    open_at(page, stack, f"?t={end - 1_800_000}&span={span[0]},{span[1]}")
    assert "heat" not in address(page)
    page.check('[data-testid="heatmap-on"]')
    page.select_option('[data-testid="heatmap-cell"]', "2")
    s = wait_heatmap(page, "occupancy", 2)
    grid = s["grid"]
    assert address(page)["heat"] == "occupancy,2"
    # The page's grid is the API's for the same span.
    params = {"kind": "occupancy", "from": grid["from_ms"], "to": grid["to_ms"], "cell": 2}
    served = httpx.get(f"{stack.api_url}/api/v1/heatmap", params=params, timeout=60).json()
    assert served["cells"] == grid["cells"] and served["max"] == grid["max"] > 0
    # Every robot-second of the loaded robots' two hours (a pose a second) is on the map.
    assert grid["total"] >= stack.history.robots * 7000
    # The picture over the floor: one pixel a cell of the cells' box.
    size = page.evaluate(
        "() => { const i = document.querySelector('.leaflet-heatmap-pane img.heatmap');"
        " return i && i.complete ? [i.naturalWidth, i.naturalHeight] : null; }"
    )
    assert size == [grid["box"]["columns"], grid["box"]["rows"]]
    # Over the floor, translucent: where a cell is (away from the robots' markers and the
    # legend), the page shows the floor as it is without the layer, blended with the cell's
    # colour on the ramp at the picture's alpha.
    x, y, value = visible_cell(page, grid)
    with_layer = pixel(page, x, y)
    page.uncheck('[data-testid="heatmap-on"]')
    page.wait_for_function("() => !document.querySelector('.leaflet-heatmap-pane img.heatmap')")
    floor = pixel(page, x, y)
    page.check('[data-testid="heatmap-on"]')
    wait_heatmap(page, "occupancy", 2)
    colour = ramp(np.array([value / grid["max"]]))[0]
    blended = [
        (int(c) * ALPHA + f * (255 - ALPHA)) / 255 for c, f in zip(colour, floor, strict=True)
    ]
    assert all(abs(a - b) <= 4 for a, b in zip(with_layer, blended, strict=True)), (
        with_layer,
        blended,
        floor,
    )
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
    assert address(page)["heat"] == "speed,2" and s["grid"]["unit"] == "m/s" and s["drawn"]
    # The address reopens it.
    url = page.url
    page.goto("about:blank")
    page.goto(url)
    page.wait_for_function("() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS)
    assert wait_heatmap(page, "speed", 2)["grid"]["cells"] == s["grid"]["cells"]
    assert page.input_value('[data-testid="heatmap-kind"]') == "speed"
    assert page.input_value('[data-testid="heatmap-cell"]') == "2"
    assert page.is_checked('[data-testid="heatmap-on"]')
    # Off: no picture, no legend, nothing in the address.
    page.uncheck('[data-testid="heatmap-on"]')
    page.wait_for_function("() => !new URLSearchParams(location.search).has('heat')")
    assert page.query_selector(".leaflet-heatmap-pane img.heatmap") is None
    assert page.query_selector('[data-testid="heatmap-legend"]') is None
    assert not page.errors
