"""The timeline's map-upload marks on a long span in Chromium: on a 1 d span busier than the
change feed reads at once, every upload of the day is drawn as its mark (the API finds
uploads without reading every write: mapservice/core/upload_scan.py), and no "zoom in"
note shows.

The day is the API's own, over an in-memory history served in this process, so the feed's
read budget (`change_feed.MAX_WRITES`) is lowered here to make a small day "busy"; the
shared stack's history is left alone."""

from __future__ import annotations

import threading
import time

import pytest
import uvicorn

from mapservice.adapters.clock import SystemClock
from mapservice.api.app import create_app
from mapservice.core import change_feed
from mapservice.core.change_feed import UPLOADER_ID
from mapservice.local.checkout import TEST_UI_DIR
from mapservice.local.embedded import free_port
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event, meta_event
from tests.ui.conftest import DIST

from .test_plots_timeline import iso

TIMEOUT_MS = 60_000
HOUR, DAY = 3_600_000, 86_400_000
READ_BUDGET = 2_000


@pytest.fixture(scope="module")
def busy_day_api():
    """(API url, now, the uploads' (robot, first write, chunks)) over a day of three robots
    writing a chunk every 20 s between them (4,320 writes, over READ_BUDGET) and two uploads."""
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    now = SystemClock().now_ms() // 1000 * 1000
    store = MemoryStore()
    store.append([meta_event(now - 2 * DAY)])
    store.append(
        [
            chunk_event(
                f"r{i % 3}", now - DAY + 20_000 * i + 3_000, i % 4, i % 5, bytes([i % 5]) * 10_000
            )
            for i in range(DAY // 20_000)
        ]
    )
    floor_at, resend_at = now - 5 * HOUR + 7, now - 14 * HOUR + 10_500
    store.append(
        [
            chunk_event(UPLOADER_ID, floor_at, i // 5, i % 5, bytes([40 + i]) * 10_000)
            for i in range(20)
        ]
    )
    store.append(
        [
            chunk_event("r1", resend_at + 300 * i, i // 5 % 4, i % 5, bytes([90 + i]) * 10_000)
            for i in range(25)
        ]
    )
    settings = Settings(api_port=free_port(), ui_dir=TEST_UI_DIR)
    uv = uvicorn.Server(
        uvicorn.Config(
            create_app(settings, store, {}),
            host="127.0.0.1",
            port=settings.api_port,
            log_level="warning",
        )
    )
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(change_feed, "MAX_WRITES", READ_BUDGET)
        thread = threading.Thread(target=uv.run, daemon=True)
        thread.start()
        deadline = time.monotonic() + 20
        while not uv.started and time.monotonic() < deadline:
            time.sleep(0.05)
        yield (
            f"http://127.0.0.1:{settings.api_port}",
            now,
            [(UPLOADER_ID, floor_at, 20), ("r1", resend_at, 25)],
        )
        uv.should_exit = True
        thread.join(10)


def test_a_busy_days_uploads_are_marked_on_the_timeline(page, busy_day_api) -> None:
    url, now, uploads = busy_day_api
    span = (now - DAY, now)
    page.goto(f"{url}/?t={now - 2 * HOUR}&span={iso(span[0])},{iso(span[1])}")
    page.wait_for_function("() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS)
    marks = page.locator('[data-testid="upload-mark"]')
    page.wait_for_function(
        "(n) => document.querySelectorAll('[data-testid=upload-mark]').length === n",
        arg=len(uploads),
        timeout=TIMEOUT_MS,
    )
    assert sorted(
        int(marks.nth(i).get_attribute("data-ts")) for i in range(marks.count())
    ) == sorted(t for _, t, _ in uploads)
    # Each is drawn inside the strip at its instant.
    width = page.evaluate(
        "() => document.querySelector('[data-testid=timeline-strip] svg').width.baseVal.value"
    )
    for i in range(marks.count()):
        t, x = int(marks.nth(i).get_attribute("data-ts")), float(marks.nth(i).get_attribute("x"))
        assert abs(x - (t - span[0]) / (span[1] - span[0]) * width) < 3, (t, x)
    assert "zoom in" not in page.inner_text(".timeline-bar")
    # The whole day's feed is still more than the API reads at once: the marks came from the
    # uploads alone.
    assert (
        page.evaluate(
            f"async () => (await fetch('/api/v1/changes?from={span[0]}&to={span[1]}')).status"
        )
        == 422
    )
    assert page.errors == []
