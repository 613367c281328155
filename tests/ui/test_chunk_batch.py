"""A seek fetches the chunk pictures it lacks in a few batch requests, never one per picture."""

from __future__ import annotations

import json

from .test_replay import TIMEOUT_MS, map_hashes, open_at, shown_hashes


def test_seek_fetches_missing_pictures_in_few_batches(page, history_stack) -> None:
    """Opening at T asks for the map's pictures in a few POST /batch requests (no PNGs);
    a second seek asks only for pictures the page does not have yet."""
    stack = history_stack
    asked: list[list[str]] = []
    singles: list[str] = []

    def on_request(req) -> None:
        if "/api/v1/chunk-contents/" not in req.url:
            return
        if req.url.endswith("/api/v1/chunk-contents/batch") and req.method == "POST":
            asked.append(json.loads(req.post_data)["hashes"])
        else:
            singles.append(req.url)

    page.on("request", on_request)
    t1 = stack.history.start_ms + 40 * 60_000
    open_at(page, stack, f"?t={t1}")
    first = set(map_hashes(stack, t1).values())
    assert shown_hashes(page) == map_hashes(stack, t1)
    fetched = {h for batch in asked for h in batch}
    assert first <= fetched
    assert not singles, singles[:3]
    assert len(asked) <= 8, [len(b) for b in asked]
    assert all(len(b) == len(set(b)) for b in asked)
    n = len(asked)
    t2 = stack.history.end_ms - 20 * 60_000
    seen = page.evaluate("() => window.__replay.seekTimes.length")
    page.evaluate("(t) => window.__replay.seek(t)", t2)
    page.wait_for_function(f"() => window.__replay.seekTimes.length > {seen}", timeout=TIMEOUT_MS)
    page.wait_for_function("() => window.__replay.complete", timeout=TIMEOUT_MS)
    assert shown_hashes(page) == map_hashes(stack, t2)
    again = [h for batch in asked[n:] for h in batch]
    assert len(again) == len(set(again)) and not set(again) & fetched
    assert set(map_hashes(stack, t2).values()) <= fetched | set(again)
    assert not page.errors  # type: ignore[attr-defined]
