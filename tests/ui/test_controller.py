"""The 2019 game page: drive a robot and paint the chunk under it through the 2019 REST API."""

from __future__ import annotations

import time

import httpx


def test_paint_black_reaches_the_map(page, history_stack) -> None:
    """Driving and painting black stores an all-black chunk under the robot, by its id."""
    stack = history_stack
    page.goto(f"{stack.api_url}/controller")
    page.locator('[data-testid="right"]').click()
    page.locator('[data-testid="right"]').click()
    page.locator('[data-testid="up"]').click()
    page.locator('[data-testid="paint-black"]').click()
    page.wait_for_function("() => document.body.innerText.includes('painted chunk')", timeout=30_000)
    text = page.locator("header").inner_text()
    row, column = (int(v) for v in text.split("painted chunk ")[1].split()[0].split(":"))
    deadline = time.monotonic() + 30
    found = None
    while time.monotonic() < deadline and found is None:
        chunks = httpx.get(f"{stack.api_url}/api/v1/map", timeout=30).json()["chunks"]
        found = next((c for c in chunks if (c["row"], c["column"]) == (row, column)
                      and c["robotId"] == "controller-1"), None)
        time.sleep(0.3)
    assert found is not None, "the painted chunk never reached the map"
    raw = httpx.get(f"{stack.api_url}/api/v1/chunk-contents/{found['content_hash']}",
                    params={"encoding": "raw"}).content
    assert set(raw) == {0}
    assert not page.errors
