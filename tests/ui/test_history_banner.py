"""The replay UI's banner "history not stored since HH:MM:SS UTC": shown while the
server's history inserts fail, with the server's reason as its tooltip, and gone once they
succeed again (the API over an in-memory history; the full disk itself is
tests/integration/test_disk_full.py, which needs root to mount a tmpfs)."""

from __future__ import annotations

import threading
import time

import pytest
import uvicorn

from mapservice.api.app import create_app
from mapservice.local.checkout import TEST_UI_DIR
from mapservice.local.embedded import free_port
from mapservice.runtime.insert_health import InsertHealth
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.ui.conftest import DIST

FULL = "Code: 243. DB::Exception: Cannot reserve 1.00 MiB, not enough space. (NOT_ENOUGH_SPACE)"
TIMEOUT_MS = 30_000  # the page polls every 5 s


@pytest.fixture(scope="module")
def status_api():
    """The API whose /api/v1/status reads an InsertHealth the test drives."""
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    health = InsertHealth()
    settings = Settings(api_port=free_port(), ui_dir=TEST_UI_DIR)
    app = create_app(
        settings, MemoryStore(), {"history_store": health}, history_status=health.status
    )
    uv = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=settings.api_port, log_level="warning")
    )
    thread = threading.Thread(target=uv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not uv.started and time.monotonic() < deadline:
        time.sleep(0.05)
    yield f"http://127.0.0.1:{settings.api_port}", health
    uv.should_exit = True
    thread.join(10)


def test_the_banner_shows_while_history_is_not_stored_and_goes_once_it_is(page, status_api) -> None:
    """No banner while inserts succeed; "history not stored since <first failure> UTC" with
    the reason while they fail; gone again after the next successful insert."""
    url, health = status_api
    health.stored()
    page.goto(f"{url}/")
    banner = page.locator('[data-testid="history-banner"]')
    page.wait_for_timeout(1500)  # the first poll has answered
    assert banner.count() == 0
    health.failed(RuntimeError(FULL))
    banner.wait_for(timeout=TIMEOUT_MS)
    since = time.strftime("%H:%M:%S", time.gmtime(health.failing_since_s))
    assert banner.inner_text().strip() == f"⚠ history not stored since {since} UTC"
    assert "NOT_ENOUGH_SPACE" in banner.get_attribute("title")
    health.stored()
    banner.wait_for(state="detached", timeout=TIMEOUT_MS)
    assert not page.errors  # type: ignore[attr-defined]
