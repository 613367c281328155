"""A page at rest costs next to nothing: paused, its seek drawn and settled, the replay asks
for no animation frame and re-renders nothing (replay-ui/src/lib/framepace.ts), while its
"ago" readout still follows the wall clock; what changes something wakes it at once."""

from __future__ import annotations

import time

from .conftest import open_replay
from .test_replay import TIMEOUT_MS

# Counts the animation frames the page asks for, whoever asks (the replay's loop, Leaflet):
# installed before the page's scripts, so it holds on any build of the page.
COUNT_FRAMES = """
window.__framesAsked = 0;
const raf = window.requestAnimationFrame.bind(window);
window.requestAnimationFrame = (cb) => raf((t) => { window.__framesAsked++; cb(t); });
"""

REST_S = 2.0


def _counts(page) -> dict:
    return page.evaluate(
        "() => ({frames: window.__framesAsked, renders: window.__replay.pace.renders,"
        " ago: document.querySelector('.ago').textContent})"
    )


def test_a_paused_page_at_rest_asks_for_no_frame_and_renders_nothing_until_woken(
    page, history_stack
) -> None:
    stack = history_stack
    page.add_init_script(COUNT_FRAMES)
    # Fifty minutes back (within the history, whenever this runs): the "ago" readout changes
    # every second; the timeline's span (an hour around it) ends long before now, so no
    # panel has a reason to read again while the page rests.
    t = max(stack.history.start_ms + 60 * 60_000, time.time_ns() // 1_000_000 - 50 * 60_000)
    open_replay(page, stack.api_url, f"?t={t}", timeout_ms=TIMEOUT_MS)
    page.wait_for_function(
        "() => window.__replay.complete && !window.__replay.seeking", timeout=TIMEOUT_MS
    )
    # The playhead settles (engine.ts SETTLE_MS) and what it then asks for (the look-ahead,
    # the exact robots, the timeline's density) lands.
    time.sleep(1.5)
    before = _counts(page)
    time.sleep(REST_S)
    after = _counts(page)
    assert after["frames"] == before["frames"], (before, after)
    assert after["renders"] == before["renders"], (before, after)
    assert after["ago"] != before["ago"], "the ago readout stood still"

    # A step wakes it: the playhead moves, the page draws and its readouts show it.
    page.click("[data-testid=step-fwd]")
    shown = time.strftime("%H:%M:%S", time.gmtime((t + 1000) // 1000))
    page.wait_for_function(
        f"() => window.__replay.playhead === {t + 1000} && window.__replay.complete"
        f" && document.querySelector('[data-testid=playhead]').textContent.includes('{shown}')"
        f" && document.querySelector('#picker').value.endsWith('{shown}')",
        timeout=TIMEOUT_MS,
    )
    woken = _counts(page)
    assert woken["frames"] > after["frames"]
    assert woken["renders"] > after["renders"]
