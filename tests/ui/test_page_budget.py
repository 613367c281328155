"""One page, one budget: a page shares the API's read budget with the other tabs of its
address (the server serves them in turns, api/fair_share.py; the page waits for its turn
and asks again after a busy answer's Retry-After, replay-ui/src/lib/request.ts), and a
live page at rest asks the server little besides its WebSocket (replay-ui/src/lib/cadence.ts)."""

from __future__ import annotations

import time
from datetime import datetime
from urllib.parse import parse_qs, urlparse

import httpx

from .conftest import ARTIFACTS, open_replay
from .test_replay import TIMEOUT_MS, map_hashes, shown_hashes

# A live page at rest: at most one request every two seconds besides the WebSocket.
IDLE_WINDOW_S = 30
IDLE_MAX_REQUESTS = IDLE_WINDOW_S // 2

# Tab 1 plays the history at 3600x over and over while the second tab opens: back to the
# start whenever it is near the end (or went live).
REPLAY_LOOP = """([start, end]) => {
  const r = window.__replay;
  r.play(3600, 1);
  window.__loop = setInterval(() => {
    if (r.seeking) return;
    if (r.live || r.playhead > end) r.seek(start).then(() => r.play(3600, 1));
  }, 100);
}"""


def _api_responses(page, into: list) -> None:
    page.on(
        "response",
        lambda r: into.append((r.status, r.url)) if "/api/" in r.url else None,
    )


def test_a_second_tab_opened_during_a_3600x_replay_draws_its_instant_without_a_refusal(
    page, browser, history_stack
) -> None:
    """Tab 1 replays at 3600x; a shared link opened in a second window (a browser context
    of its own: its own six connections, as a second worker's browser at the same address)
    draws the whole floor at the link's instant and keeps it; neither sees a 429 (or a
    503): the second one's reads wait their turn beside the first's instead of being
    refused. (Two tabs of one context share six connections, never more than the old
    per-address cap of eight at once.)"""
    stack = history_stack
    start = stack.history.start_ms + 5 * 60_000
    end = stack.history.end_ms - 20 * 60_000
    first: list[tuple[int, str]] = []
    _api_responses(page, first)
    open_replay(page, stack.api_url, f"?t={start}", timeout_ms=TIMEOUT_MS)
    page.evaluate(REPLAY_LOOP, [start, end])
    time.sleep(2.0)  # the replay's reads under way
    assert page.evaluate("() => window.__replay.playing()")

    t = stack.history.start_ms + 100 * 60_000
    link = f"?t={t}&view=-1,-300,500"
    window = browser.new_context(viewport={"width": 1280, "height": 800})
    second = window.new_page()
    seen: list[tuple[int, str]] = []
    _api_responses(second, seen)
    errors: list[str] = []
    second.on("pageerror", lambda e: errors.append(str(e)))
    try:
        open_replay(second, stack.api_url, link, timeout_ms=TIMEOUT_MS)
        second.wait_for_timeout(1500)  # whatever it reads once drawn, still beside tab 1
        assert second.evaluate("() => window.__replay.playhead") == t
        assert shown_hashes(second) == map_hashes(stack, t)
        # The address still names the link's instant.
        named = parse_qs(urlparse(second.url).query)["t"][0]
        assert datetime.fromisoformat(named.replace("Z", "+00:00")).timestamp() * 1000 == t
        assert not second.locator('[data-testid="page-error"]').count()
        second.screenshot(path=str(ARTIFACTS / "second_tab_during_3600x.png"))
    finally:
        page.evaluate("() => clearInterval(window.__loop)")
        window.close()
    refused = [(s, u) for s, u in seen + first if s in (429, 503)]
    assert not refused, f"{len(refused)} refusals reached the pages: {refused[:5]}"
    assert len(first) > 20, "tab 1 should have read while replaying"
    assert not errors and not page.errors


def _idle_requests(page, stack, query: str) -> list[str]:
    """The requests of a live page at rest over IDLE_WINDOW_S, besides its WebSocket."""
    open_replay(page, stack.api_url, query, timeout_ms=TIMEOUT_MS)
    page.wait_for_function("() => window.__replay.liveStatus.connected", timeout=TIMEOUT_MS)
    page.wait_for_timeout(3000)  # what the first frames ask for once
    asked: list[str] = []
    page.on(
        "request",
        lambda r: asked.append(f"{r.method} {r.url}") if r.resource_type != "websocket" else None,
    )
    page.wait_for_timeout(IDLE_WINDOW_S * 1000)
    print(f"\nidle live page {query}: {len(asked)} requests in {IDLE_WINDOW_S} s: {asked}")
    assert page.evaluate("() => window.__replay.live")
    assert not page.errors
    return asked


def test_an_idle_live_page_asks_at_most_once_every_two_seconds(page, history_stack) -> None:
    """Live, nothing happening: over IDLE_WINDOW_S the page sends at most one request
    every two seconds besides its WebSocket (the lists the stream does not carry are read
    again at one cadence, a sliding span is read ahead, the status is not polled apace)."""
    asked = _idle_requests(page, history_stack, "?live=1")
    assert len(asked) <= IDLE_MAX_REQUESTS, asked


def test_an_idle_live_page_with_every_panel_open_keeps_the_budget(page, history_stack) -> None:
    """The same with every panel open, a robot selected and plotted: the fleet list's
    speeds come from the live stream (no read of the poses every two seconds), and the
    panels' lists are read again only at the page's cadence or once their span slid (new
    incidents come on the stream)."""
    stack = history_stack
    robot = sorted(
        r["robotId"]
        for r in httpx.get(f"{stack.api_url}/api/v1/robots", timeout=30).json()["robots"]
    )[0]
    asked = _idle_requests(
        page,
        stack,
        f"?live=1&sel={robot}&plot={robot}&panels=changes,fleet,conflicts,plots,annotations,incidents",
    )
    assert page.locator('[data-testid="fleet-row"]').count() > 0
    assert not [a for a in asked if "/api/v1/poses?" in a], asked
    assert len(asked) <= IDLE_MAX_REQUESTS, asked
