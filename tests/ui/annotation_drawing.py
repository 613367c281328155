"""Drawing and reading the replay UI's annotations in Chromium, shared by the browser tests
on the shared UI stack and the acceptance test on a fresh `mapservice up`."""

from __future__ import annotations

from collections.abc import Sequence

TIMEOUT_MS = 60_000


def give_token(page, token: str) -> None:
    field = page.locator('[data-testid="operator-token"]')
    field.fill(token)
    field.dispatch_event("change")


def drawn(page) -> dict:
    return page.evaluate("() => window.__replay.annotations()")


def screen(page, x: float, y: float) -> tuple[float, float]:
    p = page.evaluate("([x, y]) => window.__replay.screenPointOfMetres(x, y)", [x, y])
    return p["x"], p["y"]


def center_on_metres(page, meta: dict, x: float, y: float) -> None:
    """Centres the map on (x, y) m at zoom 0: one screen pixel is one map pixel."""
    row = meta["height"] - (y - meta["origin"][1]) / meta["resolution"]
    col = (x - meta["origin"][0]) / meta["resolution"]
    page.evaluate("([r, c]) => window.__replay.centerOnPixel(r, c, 0)", [row, col])


def draw_zone_by_mouse(page, corners: Sequence[tuple[float, float]]) -> None:
    """With the draw tool: a click on each corner, a double-click on the last closes it."""
    page.click('[data-testid="draw-zone"]')
    for x, y in corners[:-1]:
        page.mouse.click(*screen(page, x, y))
    assert drawn(page)["vertices"] == len(corners) - 1
    page.mouse.dblclick(*screen(page, *corners[-1]))


def seek_and_read(page, t: int) -> dict:
    """Seeks to t and waits until the annotations at t are read and drawn. An instant
    still ahead of the page's clock (an edit's time plus a second, just after the edit) is
    waited for first: the replay clamps a seek to now, and would stop short of t."""
    page.wait_for_function("(t) => Date.now() > t", arg=t, timeout=TIMEOUT_MS)
    page.evaluate("(t) => window.__replay.seek(t)", t)
    # The page reads the annotations again only when the seek crosses an edit (or leaves the
    # span whose edits it knows): the list read at an earlier instant with no edit between
    # is the list at t.
    page.wait_for_function(
        """(t) => {
            const r = window.__replay;
            if (r.playhead !== t || !r.complete) return false;
            const a = r.annotations();
            if (!a.settled) return false;  // read before the store held this page's edit
            if (a.loadedAt === t) return true;
            const lo = Math.min(a.loadedAt, t), hi = Math.max(a.loadedAt, t);
            return Number.isFinite(a.loadedAt) && !a.marks.some(([, ts]) => ts > lo && ts <= hi);
        }""",
        arg=t,
        timeout=TIMEOUT_MS,
    )
    page.wait_for_timeout(400)  # the next summary redraws what was read
    return drawn(page)
