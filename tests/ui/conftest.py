"""A running service with three hours of loaded history, and headless Chromium on the UI.

The history is written by the bulk loader into the stack's embedded ClickHouse before the
server opens it; then brokers, server (API + processors) and gateway run as in `make up`,
so live mode sees poses published with mosquitto_pub. Chromium is Debian's, driven by
Playwright (no browser download).
"""

from __future__ import annotations

import time

import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import load_ros_map
from mapservice.bench.history_loader import load_history
from mapservice.local.checkout import TEST_UI_DIR, TEST_UI_ENV
from mapservice.local.stack import Stack
from mapservice.testing.chromium import chromium_path, launch
from tests.fixtures.paths import MAPS, ROOT
from tests.integration.conftest import run_stack

# Every browser test serves the UI's test build, which holds window.__replay.
DIST = TEST_UI_DIR / "index.html"
ARTIFACTS = ROOT / "test-artifacts" / "ui"
HOURS = 3
ROBOTS = 3


def pytest_collection_modifyitems(items):
    for item in items:
        if "/tests/ui/" in str(item.fspath):
            item.add_marker(pytest.mark.integration)


@pytest.fixture(scope="session")
def history_stack(tmp_path_factory):
    """The whole service on 127.0.0.1 over HOURS of history ending ten minutes ago."""
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    stack = Stack(
        tmp_path_factory.mktemp("ui-stack"),
        mqtt="mosquitto",
        extra_env={**TEST_UI_ENV, "MAPSERVICE_SNAPSHOT_EVERY_S": "600"},
    )
    settings = stack.settings()
    ros_map = load_ros_map(MAPS / "warehouse.yaml")
    store = ClickHouseStore(
        settings.resolved_clickhouse_dsn,
        settings.clickhouse_database,
        settings.retention_days,
        snapshot_every_ms=600_000,
    )
    end = time.time_ns() // 1_000_000 - 600_000
    try:
        result = load_history(
            store, ros_map, days=HOURS / 24, robots=ROBOTS, end_ms=end, change_prob=0.3
        )
    finally:
        store.close()
    run_stack(stack, result.meta)
    stack.history = result  # type: ignore[attr-defined]
    yield stack
    stack.stop()


def playwright_browser():
    """Debian's Chromium through Playwright, for as long as the generator is open.

    While it is, Playwright's sync API keeps an event loop running in the main thread, and
    asyncio.run() or a second sync_playwright() fails there: every browser is of module
    scope, so whatever module a test worker runs next is not affected."""
    from playwright.sync_api import sync_playwright

    if chromium_path() is None:
        pytest.fail("Chromium is missing: apt-get install chromium (or `make system-deps` as root)")
    with sync_playwright() as pw:
        b = launch(pw)
        yield b
        b.close()


@pytest.fixture(scope="module")
def browser():
    yield from playwright_browser()


@pytest.fixture(scope="module")
def module_browser():
    yield from playwright_browser()


REPLAY_READY = "() => window.__replay && window.__replay.complete"


def open_replay(page, api: str, query: str = "", timeout_ms: int = 90_000) -> None:
    """Opens the replay served at `api` (`query`: `?t=...` and the like) and waits until it
    has drawn everything that view asked for."""
    page.goto(f"{api}/{query}")
    page.wait_for_function(REPLAY_READY, timeout=timeout_ms)


@pytest.fixture
def page(browser, request):
    """A fresh 1280x800 page; a screenshot of it is saved under test-artifacts/ui/."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.errors = errors  # type: ignore[attr-defined]
    yield pg
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        pg.screenshot(path=str(ARTIFACTS / f"{request.node.name}.png"))
    finally:
        context.close()
