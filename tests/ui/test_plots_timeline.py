"""Plots and the timeline in Chromium, against a running service with loaded history: the
battery, speed and distance plots equal the stored poses, each robot in its own colour
(the same as its fleet-list swatch), the playhead drawn on them and a click seeking; the
timeline's labelled axis, counts on hover, small buckets visible beside the busiest, zoom
and back; and an address that reopens the span and the plotted robots. Screenshots go to
test-artifacts/ui/ and, with MAPSERVICE_UPDATE_SCREENSHOTS=1, to docs/."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from urllib.parse import parse_qs, urlparse

from .test_investigator import TIMEOUT_MS, api, loaded_robots, open_at, screenshot

MIN_BAR_PX = 3  # replay-ui/src/lib/timeline.ts


def iso(ms: int) -> str:
    return datetime.fromtimestamp(ms / 1000, UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def battery_pct(level: float | None, percent: bool) -> int | None:
    """A level in whole percent on its robot's scale: `percent` for a robot that ever
    reported more than 1 (its 4.3 is 4 %), else a fraction (its 0.8 is 80 %)."""
    if level is None:
        return None
    pct = level if percent else level * 100
    return math.floor(min(100, max(0, pct)) + 0.5)


def raw_buckets(poses: list[dict], bucket_ms: int) -> dict[int, dict]:
    """A plain fold of raw poses (GET /api/v1/poses) per bucket [k*bucket_ms, ...): each step
    between consecutive poses counted in the bucket of its later pose."""
    out: dict[int, dict] = {}
    poses = sorted(poses, key=lambda p: p["ts_ms"])
    for i, p in enumerate(poses):
        b = out.setdefault(
            p["ts_ms"] // bucket_ms * bucket_ms, {"distance": 0.0, "step_ms": 0, "levels": []}
        )
        if p["battery_level"] is not None:
            b["levels"].append(p["battery_level"])
        if i:
            q = poses[i - 1]
            b["distance"] += math.dist(p["position"][:2], q["position"][:2])
            b["step_ms"] += p["ts_ms"] - q["ts_ms"]
    return out


def test_plots_equal_the_stored_poses_on_the_replay_clock(page, history_stack) -> None:
    """Open an address with a robot selected, another pinned to the plots and a span: the
    plots show both robots over exactly that span, in round buckets; per bucket, the
    battery's mean and min-max band (in %) are those of the stored poses in it, the
    distance the sum of the stored steps ending in it and the speed that over the steps'
    time; each line has the robot's fleet-list colour; the playhead is drawn on the plot;
    a click on the plot seeks there."""
    stack = history_stack
    # The loaded robot-0000's battery falls 1 % a minute from 100 over 100-minute cycles: the
    # span holds the minutes where it reads 5 % or less (a level a 0-5 scale would misread),
    # whatever the hour the history ends at.
    cycle, low = 100 * 60_000, 97 * 60_000
    latest = stack.history.end_ms - 15 * 60_000
    low_at = (latest - low) // cycle * cycle + low
    t = low_at + 5 * 60_000
    span = (t - 40 * 60_000, t + 10 * 60_000)
    assert span[0] >= stack.history.start_ms, "the history is too short for the span"
    robots = loaded_robots(stack, t)
    chosen, pinned = robots[0], robots[1]
    plot_reads = []  # (from, to) of every plot read

    def on_request(request) -> None:
        if urlparse(request.url).path.endswith("/track-buckets"):
            query = parse_qs(urlparse(request.url).query)
            plot_reads.append((int(query["from"][0]), int(query["to"][0])))

    page.on("request", on_request)
    open_at(
        page,
        stack,
        f"?t={t}&sel={chosen}&plot={pinned}&panels=plots,fleet&span={iso(span[0])},{iso(span[1])}",
    )
    assert page.evaluate("() => window.__replay.span()") == list(span)
    # Wait for the span's read (answered, both robots drawn).
    page.wait_for_function(
        f"() => {{ const p = window.__replay.plots(); return p && p.robots['{chosen}']"
        f" && p.robots['{pinned}'] && p.robots['{chosen}'].mid.length > 10"
        f" && p.from === {span[0]}; }}",
        timeout=TIMEOUT_MS,
    )
    plots = page.evaluate("() => window.__replay.plots()")
    bucket = plots["bucketMs"]
    assert 1000 <= bucket <= 60_000 and 60_000 % bucket == 0, bucket
    # No read of another span first (the panel is mounted before the timeline strip: it
    # reads the span the strip starts on, the address's, not the last hour).
    assert plot_reads and all(r == (span[0], span[1] + 1) for r in plot_reads), plot_reads
    assert [
        c.get_attribute("data-robot") for c in page.locator('[data-testid="plot-robot"]').all()
    ] == [chosen, pinned]
    for rid in (chosen, pinned):
        stored = raw_buckets(
            api(
                stack,
                "/api/v1/poses",
                **{"from": span[0], "to": span[1] + 1, "robotId": rid, "limit": 100_000},
            ),
            bucket,
        )
        shown = plots["robots"][rid]
        # The loaded robots report percent: the span holds levels above 1 (and some at or
        # below 5 at some hours, which a per-sample guess would read as a 0-5 scale).
        percent = max(level for b in stored.values() for level in b["levels"]) > 1
        starts = [e // bucket * bucket for e in shown["edges"][:-1]]
        assert [s for s, d in zip(starts, shown["battery"]) if d is not None] == sorted(stored)
        for k, start in enumerate(starts):
            b = stored.get(start)
            if b is None:
                assert shown["battery"][k] is None and shown["bucketDistance"][k] == 0
                continue
            levels = b["levels"]
            # The band's ends are the lowest and highest level in % on the robot's scale.
            ends = [battery_pct(min(levels), percent), battery_pct(max(levels), percent)]
            assert [shown["batteryMin"][k], shown["batteryMax"][k]] == ends
            assert abs(shown["battery"][k] - battery_pct(sum(levels) / len(levels), percent)) <= 1
            assert math.isclose(
                shown["bucketDistance"][k], b["distance"], rel_tol=1e-6, abs_tol=1e-6
            )
            if b["step_ms"]:
                assert math.isclose(
                    shown["speed"][k], b["distance"] / (b["step_ms"] / 1000), rel_tol=1e-6
                )
        total = sum(b["distance"] for b in stored.values())
        assert math.isclose(shown["distance"][-1], total, rel_tol=1e-6)
        assert total > 1, "the robot should drive in 50 minutes"
        assert len({b for b in shown["batteryMin"] if b is not None}) > 1, (
            "the battery should change over 50 minutes"
        )

    # Who is who: each line in its robot's colour, the colour of its swatch in the fleet list.
    page.wait_for_selector(f'[data-testid="fleet-row"][data-robot="{pinned}"]', timeout=TIMEOUT_MS)
    colours = page.evaluate(
        """(ids) => {
      const rgb = (c) => { const d = document.createElement('div'); d.style.color = c; document.body.append(d);
                           const v = getComputedStyle(d).color; d.remove(); return v; };
      const u = window.__replay.engine && document.querySelector('[data-plot=battery]');
      return ids.map(id => [rgb(window.__replay.plots().robots[id].colour),
        getComputedStyle(document.querySelector(`[data-testid=fleet-row][data-robot="${id}"] .dot`)).backgroundColor,
        getComputedStyle(document.querySelector(`[data-testid=plot-robot][data-robot="${id}"] .dot`)).backgroundColor]);
    }""",
        [chosen, pinned],
    )
    for plotted, fleet_dot, chip in colours:
        assert plotted == fleet_dot == chip
    assert colours[0][0] != colours[1][0]
    # The lines themselves are drawn in those colours: some pixels of the battery canvas are.
    drawn = page.evaluate(
        """(cols) => {
      const cv = document.querySelector('[data-plot=battery] canvas');
      const d = cv.getContext('2d').getImageData(0, 0, cv.width, cv.height).data;
      const want = cols.map(c => c.match(/\\d+/g).map(Number));
      const n = want.map(() => 0);
      for (let i = 0; i < d.length; i += 4) want.forEach((w, k) => {
        if (Math.abs(d[i] - w[0]) < 3 && Math.abs(d[i + 1] - w[1]) < 3 && Math.abs(d[i + 2] - w[2]) < 3) n[k]++; });
      return n;
    }""",
        [c[0] for c in colours],
    )
    assert all(n > 20 for n in drawn), drawn

    # The playhead, drawn on the plot where its time is.
    def playhead_red() -> bool:
        return page.evaluate("""() => {
          const x = window.__replay.plotX(window.__replay.playhead);
          const over = document.querySelector('[data-plot=battery] .u-over');
          const cv = document.querySelector('[data-plot=battery] canvas');
          const r = devicePixelRatio, cb = cv.getBoundingClientRect(), ob = over.getBoundingClientRect();
          const px = Math.round((ob.left - cb.left + x) * r), py = Math.round((ob.top - cb.top + ob.height / 2) * r);
          const d = cv.getContext('2d').getImageData(px, py, 1, 1).data;
          return d[0] > 180 && d[1] < 80 && d[2] < 80;
        }""")

    page.wait_for_function("() => window.__replay.plotX(window.__replay.playhead) !== null")
    assert playhead_red()
    screenshot(page, "ui-plots.png")

    # A click on the plot seeks to the instant under the pointer.
    target = span[0] + 15 * 60_000
    # In a short window the plots scroll within their part of the page: the plot in view first.
    page.locator('[data-plot="speed"] .u-over').scroll_into_view_if_needed()
    over = page.locator('[data-plot="speed"] .u-over').bounding_box()
    x = page.evaluate(f"() => window.__replay.plotX({target})")
    page.mouse.click(over["x"] + x, over["y"] + over["height"] / 2)
    ms_per_px = (span[1] - span[0]) / over["width"]
    page.wait_for_function(
        f"() => Math.abs(window.__replay.playhead - {target}) <= {ms_per_px * 1.5}"
        " && window.__replay.complete",
        timeout=TIMEOUT_MS,
    )
    page.wait_for_timeout(400)
    assert playhead_red()
    # The address keeps the span, the plots panel and the pinned robot.
    q = page.evaluate("() => Object.fromEntries(new URLSearchParams(location.search))")
    assert (
        q["span"] == f"{iso(span[0])},{iso(span[1])}" and q["plot"] == pinned and q["sel"] == chosen
    )
    assert "plots" in q["panels"].split(",")
    assert page.errors == []


def test_timeline_reads_counts_and_zooms_back(page, history_stack) -> None:
    """The timeline over the loaded history, from an address with its span: labelled UTC
    ticks where their times are; hovering a bucket reads out its counts as the API has
    them; the quietest bucket with a change is a visible bar next to the busiest; a drag
    zooms in, the zoom-out button widens, and "back" walks the zoom history back to the
    address's span."""
    stack = history_stack
    h = stack.history
    span = (h.start_ms, h.end_ms)
    t = h.end_ms - 60 * 60_000
    open_at(page, stack, f"?t={t}&span={iso(span[0])},{iso(span[1])}")
    assert page.evaluate("() => window.__replay.span()") == list(span)
    page.wait_for_function(
        f"() => {{ const d = window.__replay.timeline(); return d && d.from_ms === {span[0]}; }}",
        timeout=TIMEOUT_MS,
    )
    tl = page.evaluate("() => window.__replay.timeline()")
    strip = page.locator('[data-testid="timeline-strip"]').bounding_box()
    width = page.evaluate(
        "() => document.querySelector('[data-testid=timeline-strip] svg').width.baseVal.value"
    )

    def x_of(ms: float) -> float:
        return (ms - span[0]) / (span[1] - span[0]) * width

    # A labelled axis: HH:MM of each tick, placed at its time, a few of them.
    ticks = page.evaluate(
        "() => [...document.querySelectorAll('[data-testid=timeline-axis] text')]"
        ".map(e => [+e.dataset.t, e.textContent, +e.getAttribute('x')])"
    )
    assert len(ticks) >= 4
    for ms, label, x in ticks:
        at = datetime.fromtimestamp(ms / 1000, UTC)
        # A tick at midnight names its day.
        assert label == at.strftime("%m-%d %H:%M" if ms % 86_400_000 == 0 else "%H:%M")
        assert abs(x - x_of(ms)) < 0.5 and span[0] <= ms <= span[1]

    # Counts on hover, as the API counts them.
    fresh = api(
        stack,
        "/api/v1/timeline",
        **{"from": tl["from_ms"], "to": tl["to_ms"], "buckets": len(tl["buckets"])},
    )
    assert fresh["buckets"] == tl["buckets"]
    # A map upload's writes are left out of its buckets' bars (test_timeline_marks checks
    # that): the session's service is shared, and another test may have uploaded into the
    # span. Those buckets are not compared here.
    uploads = api(
        stack, "/api/v1/changes", kind="upload", **{"from": tl["from_ms"], "to": tl["to_ms"]}
    )["changes"]

    def holds_an_upload(b: dict) -> bool:
        end = b["start_ms"] + tl["bucket_ms"]
        return any(
            u["ts_ms"] < end and u.get("end_ms", u["ts_ms"]) >= b["start_ms"] for u in uploads
        )

    floor = [b for b in tl["buckets"] if not holds_an_upload(b)]
    with_changes = [b for b in floor if b["chunk_changes"] > 0]
    quiet = min(with_changes, key=lambda b: b["chunk_changes"])
    busiest = max(with_changes, key=lambda b: b["chunk_changes"])
    mid = quiet["start_ms"] + tl["bucket_ms"] / 2
    page.mouse.move(strip["x"] + x_of(mid), strip["y"] + 20)
    n = quiet["chunk_changes"]
    hover = page.inner_text('[data-testid="timeline-hover"]')
    assert (
        f"{n} chunk change{'s' if n != 1 else ''} · {quiet['conflicts']} conflict" in hover
        and f"{quiet['robots_active']} robot" in hover
    ), hover
    # Bars on a square-root scale with a floor: every bucket with a change is visible, its
    # height grows with its count (the loaded history has no spike; the unit tests
    # check one change beside a 187-chunk upload).
    heights = page.evaluate(
        "() => [...document.querySelectorAll('.strip rect.bar')].map(r => [+r.getAttribute('x'),"
        " +r.getAttribute('height')])"
    )
    by_x = {round(x, 3): hgt for x, hgt in heights}
    # The busiest bucket's bar is full height; with an upload in the span, the busiest is
    # whichever bucket has the most writes left once the upload's are out, so the scale is
    # read off the busiest bucket without an upload.
    top = busiest["chunk_changes"]
    if len(floor) < len(tl["buckets"]):
        h_top = by_x[round(x_of(busiest["start_ms"]), 3)]
        top = top * ((36 - MIN_BAR_PX) / (h_top - MIN_BAR_PX)) ** 2
    for b in floor:
        shown = by_x[round(x_of(b["start_ms"]), 3)]
        c = b["chunk_changes"]
        assert math.isclose(
            shown,
            0 if c == 0 else MIN_BAR_PX + (36 - MIN_BAR_PX) * math.sqrt(c / top),
            abs_tol=1e-6,
        ), (b, shown, top, uploads)
    assert by_x[round(x_of(quiet["start_ms"]), 3)] >= MIN_BAR_PX
    screenshot(page, "ui-timeline.png")

    # Zoom in by dragging over the middle third, then out, then back twice.
    page.mouse.move(strip["x"] + width / 3, strip["y"] + 20)
    page.mouse.down()
    page.mouse.move(strip["x"] + width / 2, strip["y"] + 20, steps=4)
    page.mouse.move(strip["x"] + 2 * width / 3, strip["y"] + 20, steps=4)
    page.mouse.up()
    zoomed = page.evaluate("() => window.__replay.span()")
    assert (
        span[0] < zoomed[0] < zoomed[1] < span[1]
        and zoomed[1] - zoomed[0] < (span[1] - span[0]) / 2
    )
    page.wait_for_function(
        "() => new URLSearchParams(location.search).get('span') !== null"
        f" && !new URLSearchParams(location.search).get('span').startsWith('{iso(span[0])}')"
    )
    page.click('[data-testid="zoom-out"]')
    wider = page.evaluate("() => window.__replay.span()")
    assert math.isclose(wider[1] - wider[0], 2 * (zoomed[1] - zoomed[0]), rel_tol=1e-6)
    assert page.inner_text('[data-testid="zoom-back"]') == "⟲ back (2)"
    page.click('[data-testid="zoom-back"]')
    assert page.evaluate("() => window.__replay.span()") == zoomed
    page.click('[data-testid="zoom-back"]')
    assert page.evaluate("() => window.__replay.span()") == list(span)
    assert page.is_disabled('[data-testid="zoom-back"]')
    assert page.errors == []


def test_timeline_marks_a_map_upload_where_the_api_lists_it(page, history_stack) -> None:
    """The timeline asks the change feed for the span's map uploads and draws each as one
    mark over its writes, named on hover. The loaded history holds no upload (and the
    session's service is shared by the other UI tests), so the browser is handed one: the
    API's own answer for the span with one upload entry added."""
    import json

    stack = history_stack
    h = stack.history
    span = (h.end_ms - 60 * 60_000, h.end_ms)
    up = {
        "kind": "upload",
        "ts_ms": span[0] + 20 * 60_000,
        "row": 0,
        "column": 0,
        "robot_id": "floor-uploader",
        "content_hash": "00" * 32,
        "previous_hash": None,
        "chunks": 187,
        "end_ms": span[0] + 20 * 60_000 + 2_000,
    }
    asked: list[str] = []

    def with_upload(route):
        asked.append(route.request.url)
        body = route.fetch().json()
        body["changes"] = [up] + body["changes"]
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    page.route("**/api/v1/changes?kind=upload*", with_upload)
    open_at(page, stack, f"?t={span[0] + 30 * 60_000}&span={iso(span[0])},{iso(span[1])}")
    page.wait_for_selector('[data-testid="upload-mark"]', timeout=TIMEOUT_MS)
    assert any(f"from={span[0]}&to={span[1]}" in u for u in asked), asked
    mark = page.locator('[data-testid="upload-mark"]')
    assert mark.count() == 1 and mark.get_attribute("data-ts") == str(up["ts_ms"])
    width = page.evaluate(
        "() => document.querySelector('[data-testid=timeline-strip] svg').width.baseVal.value"
    )
    x = (up["ts_ms"] - span[0]) / (span[1] - span[0]) * width
    assert abs(float(mark.get_attribute("x")) + 1 - x) < 0.01
    strip = page.locator('[data-testid="timeline-strip"]').bounding_box()
    page.mouse.move(strip["x"] + x + 0.5, strip["y"] + 20)
    assert "map upload by floor-uploader: 187 chunks" in page.inner_text(
        '[data-testid="timeline-hover"]'
    )
    assert page.errors == []


def test_who_is_who_labels_apart_and_the_selected_robot_in_its_colour(page, history_stack) -> None:
    """With the map zoomed far out the robots crowd together: no name label overlaps
    another or another robot's marker, and the selected robot's name is among those
    shown; its trail is drawn wide in its own colour, the colour of its fleet-list swatch."""
    stack = history_stack
    t = stack.history.end_ms - 25 * 60_000
    robots = loaded_robots(stack, t)
    chosen = robots[-1]
    open_at(page, stack, f"?t={t}&sel={chosen}&panels=fleet")
    page.evaluate("() => window.__replay.fitGrid()")
    zoom = page.evaluate("() => window.__replay.view().zoom")
    # Zoom out until the markers are within a label's width of one another.
    for _ in range(8):
        drawn = page.evaluate("() => window.__replay.drawnRobots()")
        xs = [d["x"] for d in drawn]
        ys = [d["y"] for d in drawn]
        if max(xs) - min(xs) < 40 and max(ys) - min(ys) < 40:
            break
        zoom -= 1
        centre = page.evaluate("() => window.__replay.view()")
        page.evaluate(
            f"() => window.__replay.centerOnPixel({-centre['lat']}, {centre['lng']}, {zoom})"
        )
        page.wait_for_timeout(300)
    page.wait_for_function("() => window.__replay.drawnLabels().length > 0")
    labels = page.evaluate("() => window.__replay.drawnLabels()")
    # drawnRobots() is in page coordinates, the labels in the map's.
    box = page.locator('[data-testid="map"]').bounding_box()
    drawn = {
        d["robotId"]: {"x": d["x"] - box["x"], "y": d["y"] - box["y"]}
        for d in page.evaluate("() => window.__replay.drawnRobots()")
    }
    assert chosen in [lb["robotId"] for lb in labels]

    def overlap(a, b) -> bool:
        return (
            a["x"] < b["x"] + b["w"]
            and b["x"] < a["x"] + a["w"]
            and a["y"] < b["y"] + b["h"]
            and b["y"] < a["y"] + a["h"]
        )

    for i, a in enumerate(labels):
        for b in labels[i + 1 :]:
            assert not overlap(a, b), (a, b)
        for rid, d in drawn.items():
            if rid != a["robotId"]:
                marker = {"x": d["x"] - 8, "y": d["y"] - 8, "w": 16, "h": 16}
                assert not overlap(a, marker), (a, rid)
    page.wait_for_function(
        "() => { const t = window.__replay.trail(); return t && t.points > 1; }", timeout=TIMEOUT_MS
    )
    trail = page.evaluate("() => window.__replay.trail()")
    swatch = page.evaluate(
        """([c, id]) => {
      const d = document.createElement('div'); d.style.color = c; document.body.append(d);
      const v = getComputedStyle(d).color; d.remove();
      return [v, getComputedStyle(document.querySelector(`[data-testid=fleet-row][data-robot="${id}"] .dot`)).backgroundColor];
    }""",
        [trail["colour"], chosen],
    )
    assert swatch[0] == swatch[1] and trail["weight"] >= 4
    screenshot(page, "ui-who-is-who.png")
    assert page.errors == []
