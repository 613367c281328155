"""The timeline's marks in Chromium: map uploads never counted as floor changes (their
writes leave the change bars and the hover counts, also an upload crossing buckets), and a
click on a conflict mark seeking to just after the later write of the bucket's first
conflict. The loaded history holds neither uploads nor conflicts at chosen places, and the
session's service is shared, so the browser is handed them: the API's own answers with
the upload, its writes, the conflicts and their counts added."""

from __future__ import annotations

import json
import math
from urllib.parse import parse_qs, urlparse

from .test_investigator import TIMEOUT_MS, open_at
from .test_plots_timeline import MIN_BAR_PX, iso


def _params(url: str) -> dict[str, str]:
    return {k: v[0] for k, v in parse_qs(urlparse(url).query).items()}


def _bar_heights(page) -> list[float]:
    return page.evaluate(
        "() => [...document.querySelectorAll('.strip rect.bar')]"
        ".sort((a, b) => a.getAttribute('x') - b.getAttribute('x')).map(r => +r.getAttribute('height'))"
    )


def test_upload_writes_are_not_counted_as_floor_changes(page, history_stack) -> None:
    stack = history_stack
    span = (stack.history.end_ms - 60 * 60_000, stack.history.end_ms)
    real: dict = {}
    added: dict[str, dict] = {}

    def timeline(route):
        body = route.fetch().json()
        real["tl"] = json.loads(json.dumps(body))
        n, b = len(body["buckets"]), body["bucket_ms"]
        i, j = n // 3, 2 * n // 3
        one = {"ts_ms": body["buckets"][i]["start_ms"] + 100, "chunks": 187}
        one["end_ms"] = one["ts_ms"] + min(500, b // 2)
        across = {"ts_ms": body["buckets"][j]["start_ms"] + b - 200, "chunks": 12}
        across["end_ms"] = across["ts_ms"] + 400
        added.update(one=one, across=across, i=i, j=j)
        body["buckets"][i]["chunk_changes"] += 187
        body["buckets"][j]["chunk_changes"] += 5
        body["buckets"][j + 1]["chunk_changes"] += 7
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    def uploads(route):
        body = route.fetch().json()
        body["changes"] = [
            {
                "kind": "upload",
                "row": 0,
                "column": 0,
                "robot_id": robot,
                "content_hash": "00" * 16,
                "previous_hash": None,
                **added[key],
            }
            for key, robot in (("across", "looper"), ("one", "floor-uploader"))
        ] + body["changes"]
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    def chunk_events(route):
        q, a = _params(route.request.url), added.get("across")
        if not a or int(q["from"]) != a["ts_ms"]:
            route.fallback()
            return
        body = route.fetch().json()
        body += [
            {
                "row": 0,
                "column": k,
                "timestamp": "",
                "ts_ms": t,
                "receive_time_ms": t,
                "robotId": "looper",
                "content_hash": "00" * 16,
            }
            for k, t in enumerate([a["ts_ms"]] * 5 + [a["end_ms"]] * 7)
        ]
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    page.route("**/api/v1/timeline?*", timeline)
    page.route("**/api/v1/changes?kind=upload*", uploads)
    page.route("**/api/v1/chunk-events?*", chunk_events)
    open_at(page, stack, f"?t={span[0] + 30 * 60_000}&span={iso(span[0])},{iso(span[1])}")
    page.wait_for_selector('[data-testid="upload-mark"]', timeout=TIMEOUT_MS)
    tl = real["tl"]
    counts = [b["chunk_changes"] for b in tl["buckets"]]
    top = max(1, *counts)
    want = [0 if c == 0 else MIN_BAR_PX + (36 - MIN_BAR_PX) * math.sqrt(c / top) for c in counts]
    page.wait_for_function(
        f"() => document.querySelectorAll('.strip rect.bar').length === {len(counts)}"
    )
    page.wait_for_function(
        "(i) => +[...document.querySelectorAll('.strip rect.bar')]"
        ".sort((a, b) => a.getAttribute('x') - b.getAttribute('x'))[i].getAttribute('height') "
        f"< 36 || {counts[added['i']]} === {top}",
        arg=added["i"],
        timeout=TIMEOUT_MS,
    )
    shown = _bar_heights(page)
    assert all(math.isclose(s, w, abs_tol=1e-6) for s, w in zip(shown, want)), (
        added,
        shown[:5],
        want[:5],
    )
    # The hover reads the floor's count, and the upload by name.
    width = page.evaluate(
        "() => document.querySelector('[data-testid=timeline-strip] svg').width.baseVal.value"
    )
    strip = page.locator('[data-testid="timeline-strip"]').bounding_box()
    x = (added["one"]["ts_ms"] - span[0]) / (span[1] - span[0]) * width
    page.mouse.move(strip["x"] + x + 0.5, strip["y"] + 20)
    hover = page.inner_text('[data-testid="timeline-hover"]')
    n = counts[added["i"]]
    assert (
        f"{n} chunk change{'s' if n != 1 else ''} ·" in hover
        and "map upload by floor-uploader: 187 chunks" in hover
    )
    assert page.errors == []


def test_a_click_on_a_conflict_mark_lands_after_the_later_write(page, history_stack) -> None:
    stack = history_stack
    span = (stack.history.end_ms - 60 * 60_000, stack.history.end_ms)
    marked: dict = {}

    def timeline(route):
        body = route.fetch().json()
        k = len(body["buckets"]) // 2
        start = body["buckets"][k]["start_ms"]
        marked.update(start=start, bucket_ms=body["bucket_ms"])
        body["buckets"][k]["conflicts"] = 2
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    def conflicts(route):
        q = _params(route.request.url)
        if "start" not in marked or int(q["from"]) != marked["start"]:
            route.fallback()
            return
        s = marked["start"]
        listed = [
            {
                "row": 1,
                "column": 2,
                "ts_ms": t,
                "robot_a": "a",
                "ts_a_ms": t - 3_000,
                "hash_a": None,
                "robot_b": "b",
                "hash_b": None,
                "seek_ms": t + 1,
            }
            for t in (s + 700, s + 300)
        ]
        route.fulfill(
            status=200,
            content_type="application/json",
            body=json.dumps(
                {
                    "from_ms": s,
                    "to_ms": s + marked["bucket_ms"],
                    "window_s": 60,
                    "rule": "",
                    "conflicts": listed,
                    "truncated": False,
                }
            ),
        )

    page.route("**/api/v1/timeline?*", timeline)
    page.route("**/api/v1/conflicts?*", conflicts)
    open_at(page, stack, f"?t={span[0] + 10 * 60_000}&span={iso(span[0])},{iso(span[1])}")
    tick = page.locator('[data-testid="conflict-tick"]')
    tick.first.wait_for(timeout=TIMEOUT_MS)
    assert tick.count() == 1 and int(tick.get_attribute("data-start")) == marked["start"]
    box = tick.bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    # The bucket's first conflict (by its later write), just after that write.
    page.wait_for_function(
        f"() => window.__replay.playhead === {marked['start'] + 301} && window.__replay.complete",
        timeout=TIMEOUT_MS,
    )
    assert page.errors == []
