"""The replay UI where reads need a token (MAPSERVICE_API_READ_ACCESS=token): it asks for
one, keeps it in the browser and sends it with every request, the live stream's included."""

from __future__ import annotations

import threading
import time

import pytest
import uvicorn

from mapservice.adapters.clock import SystemClock
from mapservice.api.app import create_app
from mapservice.api.live_hub import LiveHub
from mapservice.core.events import MapMetaSet, make_envelope
from mapservice.local.checkout import TEST_UI_DIR
from mapservice.local.embedded import free_port
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.ui.conftest import DIST

READER = "viewer-" + "r" * 32
TIMEOUT_MS = 30_000


@pytest.fixture(scope="module")
def token_api():
    """The API over a small in-memory history, reads by token, served by uvicorn."""
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    now = SystemClock().now_ms()
    store = MemoryStore()
    store.append(
        [make_envelope("api", now - 60_000, now - 60_000, MapMetaSet(400, 300, 100, 100, 3, 4))]
    )
    settings = Settings(
        api_port=free_port(),
        api_read_access="token",
        api_reader_tokens=READER,
        admin_token="a" * 32,
        api_writer_tokens="w" * 32,
        ui_dir=TEST_UI_DIR,
    )
    hub = LiveHub()
    uv = uvicorn.Server(
        uvicorn.Config(
            create_app(settings, store, {}, live_hub=hub),
            host="127.0.0.1",
            port=settings.api_port,
            log_level="warning",
        )
    )
    thread = threading.Thread(target=uv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not uv.started and time.monotonic() < deadline:
        time.sleep(0.05)
    yield f"http://127.0.0.1:{settings.api_port}", hub
    uv.should_exit = True
    thread.join(10)


def test_the_replay_asks_for_a_token_and_then_reads_with_it(page, token_api) -> None:
    """Without a token the page shows the 401 and a token field; with the reader token pasted the map loads and live mode connects."""
    url, hub = token_api
    page.goto(f"{url}/")
    prompt = page.locator('[data-testid="token-prompt"] input')
    prompt.wait_for(timeout=TIMEOUT_MS)
    prompt.fill(READER)
    prompt.dispatch_event("change")
    page.wait_for_load_state()
    page.wait_for_timeout(2000)  # the reloaded page's first seek
    assert page.locator('[data-testid="token-prompt"]').count() == 0
    assert page.evaluate("() => localStorage.getItem('mapservice.apiToken')") == READER
    page.locator('[data-testid="live"]').click()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not hub.subscribers:
        time.sleep(0.2)
    assert hub.subscribers >= 1, "the live stream did not connect with the token"
    assert not page.errors


def test_the_export_button_follows_the_read_rules(page, token_api) -> None:
    """Where reads need a token, the export button sends the one the page holds: with a
    wrong one the page says the export was refused (401) and what to do; with the reader
    token the visible span is saved as MCAP."""
    url, _ = token_api
    page.goto(f"{url}/")
    page.evaluate("() => localStorage.setItem('mapservice.apiToken', 'viewer-wrong')")
    page.reload()
    page.locator('[data-testid="export-button"]').wait_for(timeout=TIMEOUT_MS)
    page.select_option('[data-testid="export-kind"]', "mcap")
    page.click('[data-testid="export-button"]')
    status = page.locator('[data-testid="export-status"]')
    page.wait_for_function(
        "() => document.querySelector('[data-testid=export-status]')?.innerText.includes('401')",
        timeout=TIMEOUT_MS,
    )
    assert "token" in status.inner_text()
    page.evaluate(f"() => localStorage.setItem('mapservice.apiToken', '{READER}')")
    page.reload()
    page.locator('[data-testid="export-button"]').wait_for(timeout=TIMEOUT_MS)
    with page.expect_download(timeout=TIMEOUT_MS) as info:
        page.click('[data-testid="export-button"]')
    data = open(info.value.path(), "rb").read()
    assert data[:8] == b"\x89MCAP0\r\n"
    assert not page.errors
