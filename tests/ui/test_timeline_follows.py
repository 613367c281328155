"""The timeline follows the user, in Chromium against the shared stack with loaded history:
a drag into the past while live stays there (the page leaves live); a preset while paused
is centred on the playhead, and a copied link reopens that span and instant; a typed span
is shown, a bad one says what is wrong; Shift+→/← step through the changes with the change
feed closed; an operator's edit leaves the playhead where it was; "whole floor" fits the
floor while following a robot. Screenshots with three panels open at 1280x800 and
1920x1080 go to test-artifacts/ui/."""

from __future__ import annotations

import time

import httpx

from .annotation_drawing import give_token, screen
from .conftest import ARTIFACTS
from .test_annotations_ui import operator_token
from .test_investigator import TIMEOUT_MS, api, open_at, screenshot
from .test_plots_timeline import iso

HOUR = 3_600_000
SPAN = "() => window.__replay.span()"


def drag_on_strip(page, x0: float, x1: float) -> None:
    """A drag across the timeline strip from fraction x0 to fraction x1 of its width."""
    strip = page.locator('[data-testid="timeline-strip"]').bounding_box()
    y = strip["y"] + 20
    page.mouse.move(strip["x"] + strip["width"] * x0, y)
    page.mouse.down()
    page.mouse.move(strip["x"] + strip["width"] * (x0 + x1) / 2, y, steps=4)
    page.mouse.move(strip["x"] + strip["width"] * x1, y, steps=4)
    page.mouse.up()


def settled_at(page, t: int) -> None:
    page.wait_for_function(
        f"() => window.__replay.playhead === {t} && window.__replay.complete", timeout=TIMEOUT_MS
    )


def test_a_drag_into_the_past_while_live_stays_there(page, history_stack) -> None:
    """Live, a drag over the first half of the last hour: the timeline keeps the dragged
    span (it does not snap back to now), the page leaves live and pauses at the span's end,
    and the address holds that span and instant."""
    open_at(page, history_stack, "?live=1")
    page.wait_for_function("() => window.__replay.liveStatus.connected", timeout=TIMEOUT_MS)
    assert page.evaluate("() => window.__replay.live")
    drag_on_strip(page, 0.1, 0.5)
    dragged = page.evaluate(SPAN)
    assert dragged[1] < time.time() * 1000 - 20 * 60_000
    page.wait_for_function(
        f"() => !window.__replay.live && window.__replay.playhead === {dragged[1]}"
        " && window.__replay.complete",
        timeout=TIMEOUT_MS,
    )
    page.wait_for_timeout(1500)  # several of the page's summaries: the view stays put
    assert page.evaluate(SPAN) == dragged
    assert page.evaluate("() => window.__replay.playhead") == dragged[1]
    q = page.evaluate("() => Object.fromEntries(new URLSearchParams(location.search))")
    assert q.get("live") is None and q["t"] == iso(dragged[1])
    assert q["span"] == f"{iso(dragged[0])},{iso(dragged[1])}"
    assert page.errors == []


def test_presets_while_paused_hold_the_playhead_and_a_link_reopens_the_span(
    page, history_stack
) -> None:
    """Paused hours back, each preset shows its length centred on the playhead (cut only by
    now): the playhead stays in view and where it was; the address then reopens exactly
    that span and instant in a new tab."""
    stack = history_stack
    t = stack.history.start_ms + 30 * 60_000
    open_at(page, stack, f"?t={t}")
    for label, length in (("1h", HOUR), ("6h", 6 * HOUR), ("1d", 24 * HOUR), ("1h", HOUR)):
        page.locator(f'[data-preset="{label}"]').click()
        span = page.evaluate(SPAN)
        now = page.evaluate("() => Date.now()")
        assert span[1] - span[0] == length, (label, span)
        assert span[0] <= t <= span[1], (label, span, t)
        if t + length / 2 <= now - 5_000:
            assert span == [t - length // 2, t + length // 2], label
        else:
            assert now - 5_000 <= span[1] <= now, label
        page.wait_for_timeout(300)
        assert page.evaluate("() => window.__replay.playhead") == t
    page.wait_for_function(
        f"() => new URLSearchParams(location.search).get('span') === '{iso(t - HOUR // 2)},{iso(t + HOUR // 2)}'"
    )
    link = page.url
    other = page.context.new_page()
    try:
        open_at(other, stack, "?" + link.split("?", 1)[1])
        assert other.evaluate(SPAN) == [t - HOUR // 2, t + HOUR // 2]
        assert other.evaluate("() => window.__replay.playhead") == t
        assert not other.evaluate("() => window.__replay.live")
    finally:
        other.close()
    assert page.errors == []


def test_a_typed_span_is_shown_and_a_bad_one_says_why(page, history_stack) -> None:
    """The span's two boxes: a span typed there is shown (and the playhead, outside it,
    moves to its nearest end); an end before the start, or a word, is refused with what is
    wrong and the span shown stays."""
    stack = history_stack
    t = stack.history.end_ms - 20 * 60_000
    open_at(page, stack, f"?t={t}")
    before = page.evaluate(SPAN)
    a = (stack.history.start_ms // 1000 + 60) * 1000
    b = a + 40 * 60_000

    def typed(start: str, end: str) -> None:
        page.fill('[data-testid="span-from"]', start)
        page.fill('[data-testid="span-to"]', end)
        page.locator('[data-testid="span-to"]').press("Enter")

    def text(ms: int) -> str:
        return iso(ms)[:19].replace("T", " ")

    typed(text(b), text(a))
    assert "end must be after its start" in page.inner_text('[data-testid="span-error"]')
    assert page.evaluate(SPAN) == before
    typed("yesterday", text(b))
    assert '"yesterday" is not a time' in page.inner_text('[data-testid="span-error"]')
    assert page.evaluate(SPAN) == before
    typed(text(a), text(b))
    assert page.evaluate(SPAN) == [a, b]
    assert page.locator('[data-testid="span-error"]').count() == 0
    # The playhead (after the typed span) follows the view to its end.
    settled_at(page, b)
    page.wait_for_function(
        f"() => new URLSearchParams(location.search).get('span') === '{iso(a)},{iso(b)}'"
    )
    assert page.errors == []


def test_shift_arrows_step_through_changes_with_the_feed_closed(page, history_stack) -> None:
    """No panel open: Shift+→ goes to just after the next change in the history (as the
    change feed lists it), Shift+← back to just after the one before, each chunk outlined."""
    stack = history_stack
    t = stack.history.end_ms - 60 * 60_000
    open_at(page, stack, f"?t={t}")
    span = page.evaluate(SPAN)
    later = api(stack, "/api/v1/changes", **{"from": t, "to": t + 10 * 60_000, "limit": 1000})
    assert later["next"] is None and later["changes"], "too few or too many changes to test"
    following = min(later["changes"], key=lambda c: c["ts_ms"])
    after = (following["end_ms"] if following["kind"] == "upload" else following["ts_ms"]) + 1
    page.locator('[data-testid="map"]').click(position={"x": 5, "y": 300})
    page.keyboard.press("Shift+ArrowRight")
    settled_at(page, after)
    meta = page.evaluate("() => window.__replay.meta")
    ch, cw = meta["CHUNK_HEIGHT"], meta["CHUNK_WIDTH"]
    top, left = following["row"] * ch, following["column"] * cw
    if following["kind"] == "change":
        assert page.evaluate("() => window.__replay.outlined()") == [
            [top, left],
            [top + ch, left + cw],
        ]
    before = api(
        stack, "/api/v1/changes", **{"from": span[0], "to": following["ts_ms"], "limit": 1}
    )
    assert before["changes"], "no change before the first one after t"
    page.keyboard.press("Shift+ArrowLeft")
    settled_at(page, before["changes"][0]["ts_ms"] + 1)
    assert page.locator('[data-testid="change-feed"]').count() == 0
    assert page.errors == []


def test_an_operators_edit_leaves_the_playhead(page, history_stack) -> None:
    """Paused an hour back with the zones panel open, an operator places a point of
    interest: it is stored now, the playhead stays where the operator was looking; "show
    it" goes to the edit's instant, where the map shows the point."""
    stack = history_stack
    t = stack.history.end_ms - 60 * 60_000
    open_at(page, stack, f"?t={t}&panels=annotations")
    token = operator_token(stack)
    give_token(page, token)
    page.wait_for_selector('[data-testid="edit-panel"]', timeout=TIMEOUT_MS)
    page.evaluate("() => window.__replay.fitGrid()")
    name = f"ui-test stays {time.time_ns()}"
    page.fill('[data-testid="poi-name"]', name)
    page.click('[data-testid="place-poi"]')
    page.mouse.click(*screen(page, -4.0, -9.6))
    page.wait_for_function(
        "(n) => (document.querySelector('[data-testid=edit-status]')?.innerText ?? '').includes(n)",
        arg=name,
        timeout=TIMEOUT_MS,
    )
    stored = next(
        a
        for a in api(stack, "/api/v1/annotations")["annotations"]
        if a["annotation"]["name"] == name
    )
    page.wait_for_timeout(1000)  # several summaries: nothing moves the playhead
    assert page.evaluate("() => window.__replay.playhead") == t
    assert not page.evaluate("() => window.__replay.live")
    page.click('[data-testid="edit-show"]')
    settled_at(page, stored["changed_ms"])
    page.wait_for_selector(f'.poi[data-id="{stored["id"]}"]', timeout=TIMEOUT_MS)
    httpx.delete(
        f"{stack.api_url}/api/v1/annotations/{stored['id']}",
        headers={"Authorization": f"Bearer {token}"},
        timeout=30,
    ).raise_for_status()
    assert page.errors == []


def test_show_it_follows_the_page_leaving_and_rejoining_live(page, history_stack) -> None:
    """Live, an operator places a point: the map shows it now, so no "show it". Paused
    (nothing else changes: the status and the edit's instant stay), "show it" appears at
    once and goes to the edit's instant; back to live, it goes again."""
    stack = history_stack
    open_at(page, stack, "?live=1&panels=annotations")
    page.wait_for_function("() => window.__replay.liveStatus.connected", timeout=TIMEOUT_MS)
    token = operator_token(stack)
    give_token(page, token)
    page.wait_for_selector('[data-testid="edit-panel"]', timeout=TIMEOUT_MS)
    page.evaluate("() => window.__replay.fitGrid()")
    name = f"ui-test show it {time.time_ns()}"
    page.fill('[data-testid="poi-name"]', name)
    page.click('[data-testid="place-poi"]')
    page.mouse.click(*screen(page, -4.0, -9.6))
    page.wait_for_function(
        "(n) => (document.querySelector('[data-testid=edit-status]')?.innerText ?? '').includes(n)",
        arg=name,
        timeout=TIMEOUT_MS,
    )
    stored = next(
        a
        for a in api(stack, "/api/v1/annotations")["annotations"]
        if a["annotation"]["name"] == name
    )
    try:
        assert page.evaluate("() => window.__replay.live")
        assert page.locator('[data-testid="edit-show"]').count() == 0
        page.click('[data-testid="play-pause"]')  # leaves live where it is
        page.wait_for_selector('[data-testid="edit-show"]', timeout=5_000)
        page.click('[data-testid="edit-show"]')
        settled_at(page, stored["changed_ms"])
        page.wait_for_selector(f'.poi[data-id="{stored["id"]}"]', timeout=TIMEOUT_MS)
        page.click('[data-testid="live"]')
        page.wait_for_function("() => window.__replay.live", timeout=TIMEOUT_MS)
        page.wait_for_selector('[data-testid="edit-show"]', state="detached", timeout=5_000)
    finally:
        httpx.delete(
            f"{stack.api_url}/api/v1/annotations/{stored['id']}",
            headers={"Authorization": f"Bearer {token}"},
            timeout=30,
        ).raise_for_status()
    assert page.errors == []


def test_whole_floor_while_following_a_robot(page, history_stack) -> None:
    """Following a robot zoomed in, "whole floor" shows the floor (every corner of the grid
    in the map's box) and stops following, so the view stays there."""
    stack = history_stack
    t = stack.history.end_ms - 30 * 60_000
    robot = sorted(r["robotId"] for r in api(stack, "/api/v1/robots", at=t)["robots"])[0]
    open_at(page, stack, f"?t={t}&sel={robot}&follow={robot}&speed=60&play=1")
    page.evaluate(
        "() => { const v = window.__replay.view(); window.__replay.centerOnPixel(-v.lat, v.lng, 3); }"
    )
    page.wait_for_timeout(500)
    page.click('[data-testid="whole-floor"]')
    meta = page.evaluate("() => window.__replay.meta")
    box = page.locator('[data-testid="map"]').bounding_box()
    page.wait_for_timeout(1000)  # the robot drives on; the view stays on the floor
    for row, col in ((0, 0), (meta["height"], meta["width"])):
        p = page.evaluate("([r, c]) => window.__replay.screenPointOfPixel(r, c)", [row, col])
        assert box["x"] - 1 <= p["x"] <= box["x"] + box["width"] + 1, (row, col, p, box)
        assert box["y"] - 1 <= p["y"] <= box["y"] + box["height"] + 1, (row, col, p, box)
    assert "follow" not in page.evaluate("() => location.search")
    assert page.evaluate("() => window.__replay.selected()") == robot
    assert page.errors == []


def test_three_panels_keep_the_map_usable(browser, history_stack) -> None:
    """Changes, fleet and plots open with a robot selected, at 1280x800 and 1920x1080: the
    map keeps most of the window's height, the side bar's panels scroll within the window,
    and the screenshots are saved for a look."""
    stack = history_stack
    t = stack.history.end_ms - 30 * 60_000
    robot = sorted(r["robotId"] for r in api(stack, "/api/v1/robots", at=t)["robots"])[0]
    for w, h in ((1280, 800), (1920, 1080)):
        context = browser.new_context(viewport={"width": w, "height": h})
        page = context.new_page()
        try:
            open_at(page, stack, f"?t={t}&sel={robot}&panels=changes,fleet,plots")
            page.wait_for_selector('[data-testid="fleet-row"]', timeout=TIMEOUT_MS)
            page.wait_for_function(
                "() => { const p = window.__replay.plots(); return p && Object.keys(p.robots).length > 0; }",
                timeout=TIMEOUT_MS,
            )
            page.wait_for_timeout(500)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            screenshot(page, f"ui-three-panels-{w}x{h}.png")
            map_box = page.locator('[data-testid="map"]').bounding_box()
            assert map_box["height"] >= 0.55 * h, (w, h, map_box)
            # The selected robot's details start within the window, beside the map.
            details = page.locator('[data-testid="robot-details"]').bounding_box()
            assert details["y"] < h - 40, (w, h, details)
            # The page itself does not scroll: what is below the fold is inside a panel that does.
            assert page.evaluate("() => document.documentElement.scrollHeight") <= h
        finally:
            context.close()


# Every box that must show whole, with the box it must fit in (a box that scrolls or clips
# its content): each plot in the plots' panel, each timeline legend item in the timeline's
# bar, each plotted robot's chip in the plots' bar, every side panel within the side bar's
# width; all of them within the window.
CLIPPED = """() => {
  const box = (el) => el.getBoundingClientRect();
  const inside = (a, b) => a.left >= b.left - 0.5 && a.right <= b.right + 0.5 && a.top >= b.top - 0.5 && a.bottom <= b.bottom + 0.5;
  const within = (a, b) => a.left >= b.left - 0.5 && a.right <= b.right + 0.5;
  const view = { left: 0, top: 0, right: innerWidth, bottom: innerHeight };
  const out = [];
  // whole: inside its container and the window; else (a side panel, which the side bar
  // scrolls to) within their widths only.
  const check = (what, el, container, whole = true) => {
    const a = box(el), b = box(container);
    if (a.width === 0 || a.height === 0) out.push(`${what}: not drawn`);
    else if (!(whole ? inside(a, b) : within(a, b))) out.push(`${what} ${JSON.stringify(a)} outside ${JSON.stringify(b)}`);
    else if (!(whole ? inside(a, view) : within(a, view))) out.push(`${what} ${JSON.stringify(a)} outside the window`);
  };
  const plots = document.querySelector('[data-testid=plot-panel]');
  if (!plots) return ['no plot panel'];
  for (const p of plots.querySelectorAll('[data-plot]')) {
    const u = p.querySelector('.uplot');
    if (!u) out.push(`plot ${p.dataset.plot}: not drawn`);
    else check(`plot ${p.dataset.plot}`, u, plots);
  }
  for (const c of plots.querySelectorAll('[data-testid=plot-robot]')) check(`plot chip ${c.dataset.robot}`, c, plots);
  const bar = document.querySelector('.timeline-bar');
  const items = document.querySelectorAll('[data-testid=timeline-legend-item]');
  if (!items.length) out.push('no timeline legend');
  for (const i of items) check(`legend item ${i.textContent.trim()}`, i, bar);
  const side = document.querySelector('aside.side');
  for (const s of side.children) check(`side panel ${s.className || s.tagName}`, s, side, false);
  return out;
}"""


def test_three_side_panels_clip_no_plot_or_legend_item(browser, history_stack) -> None:
    """Changes, fleet and conflicts open beside the plots (a robot selected and plotted),
    at 1280x800 and 1920x1080: every plot shows whole within its panel, every legend item
    of the timeline and every chip of the plots within its bar, no side panel wider than the
    side bar (which scrolls), all of it within the window. Screenshots in
    test-artifacts/ui/."""
    stack = history_stack
    t = stack.history.end_ms - 30 * 60_000
    robot = sorted(r["robotId"] for r in api(stack, "/api/v1/robots", at=t)["robots"])[0]
    for w, h in ((1280, 800), (1920, 1080)):
        context = browser.new_context(viewport={"width": w, "height": h})
        page = context.new_page()
        try:
            open_at(
                page, stack, f"?t={t}&sel={robot}&plot={robot}&panels=changes,fleet,conflicts,plots"
            )
            page.wait_for_selector('[data-testid="fleet-row"]', timeout=TIMEOUT_MS)
            page.wait_for_function(
                "() => { const p = window.__replay.plots(); return p && Object.keys(p.robots).length > 0; }",
                timeout=TIMEOUT_MS,
            )
            page.wait_for_timeout(500)
            screenshot(page, f"ui-three-side-panels-{w}x{h}.png")
            assert page.evaluate(CLIPPED) == [], (w, h)
            # Nothing wider than the window: no horizontal scrolling anywhere on the page.
            assert page.evaluate("() => document.documentElement.scrollWidth") <= w
            map_box = page.locator('[data-testid="map"]').bounding_box()
            assert map_box["height"] >= 0.5 * h, (w, h, map_box)
        finally:
            context.close()
