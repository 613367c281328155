"""A figure of the plots is the same whichever zoom shows it: a robot's distance over a day,
read in the browser at the 1 h zoom (hour by hour), at 1 d and at 7 d, equals the fold of its
raw poses; each bucket's speed is its distance over its steps' time."""

from __future__ import annotations

import math

from .test_investigator import TIMEOUT_MS, api, loaded_robots, open_at, screenshot
from .test_plots_timeline import iso, raw_buckets


def raw_distance(stack, robot: str, start: int, end: int) -> float:
    """Metres between the robot's consecutive raw poses in [start, end)."""
    poses = sorted(
        api(
            stack,
            "/api/v1/poses",
            **{"from": start, "to": end, "robotId": robot, "limit": 100_000},
        ),
        key=lambda p: p["ts_ms"],
    )
    return sum(math.dist(a["position"][:2], b["position"][:2]) for a, b in zip(poses, poses[1:]))


def driven_shown(series: dict, start: int, end: int) -> float:
    """The metres a robot's distance line shows driven in [start, end): its value at the
    last of its instants (`edges`) at or before each end."""

    def at(t: int) -> float:
        shown = 0.0
        for x, d in zip(series["edges"], series["distance"]):
            if x <= t:
                shown = d
        return shown

    return at(end) - at(start)


def test_a_days_distance_reads_the_same_at_every_zoom(page, history_stack) -> None:
    """A robot's distance over a day, read through the plots at the 1 h zoom (the day's
    hours, one span each), the 1 d zoom (the day) and the 7 d zoom (the week ending with
    it, its buckets within the day), agrees within 2 % with a fold of the API's raw poses,
    and so does each bucket's speed; the panel names the span's distance beside the robot."""
    stack = history_stack
    h = stack.history
    hour, day = 3_600_000, 86_400_000
    robot = loaded_robots(stack, h.end_ms)[0]
    # A day of whole hours ending at the last whole hour of the history (the page moves a span
    # reaching past now back to end now: every span read here lies in the past).
    end = h.end_ms - h.end_ms % hour
    start = end - day
    raw = raw_distance(stack, robot, start, end)
    assert raw > 100, raw
    poses = api(
        stack, "/api/v1/poses", **{"from": start, "to": end, "robotId": robot, "limit": 100_000}
    )
    hours = sorted({p["ts_ms"] // hour * hour for p in poses})
    assert len(hours) >= 3

    def read(span: tuple[int, int]) -> dict:
        # The playhead inside the span (the history's end where it holds it).
        t = (
            min(max(h.end_ms, span[0]), span[1] - 1)
            if span[1] - span[0] > hour
            else span[0] + hour // 2
        )
        open_at(page, stack, f"?t={t}&plot={robot}&panels=plots&span={iso(span[0])},{iso(span[1])}")
        page.wait_for_function(
            f"() => {{ const p = window.__replay.plots(); return p && p.robots['{robot}']"
            f" && p.to === {span[1]}; }}",
            timeout=TIMEOUT_MS,
        )
        return page.evaluate("() => window.__replay.plots()")

    by_hours = 0.0
    for h0 in hours:
        by_hours += driven_shown(read((h0, h0 + hour))["robots"][robot], h0, h0 + hour + 1)
    by_day = read((start, end))
    # The 7 d zoom: a week's span ending with the day, short of the oldest instant kept
    # (the page moves a span reaching before it).
    week = read((end - 7 * day + 2 * hour, end))
    shown = {
        "1 h": by_hours,
        "1 d": driven_shown(by_day["robots"][robot], start, end + 1),
        "7 d": driven_shown(week["robots"][robot], start, end + 1),
    }
    assert week["bucketMs"] >= 10 * 60_000 and day % week["bucketMs"] == 0, week["bucketMs"]
    for zoom, metres in shown.items():
        assert abs(metres - raw) <= 0.02 * raw, (zoom, metres, raw, shown)
    # Speed at the day and the week zooms: each bucket's, the raw steps' over their time.
    for plots in (by_day, week):
        series, bucket = plots["robots"][robot], plots["bucketMs"]
        folded = raw_buckets(poses, bucket)
        speeds = [
            (v, folded[e // bucket * bucket])
            for e, v in zip(series["edges"][:-1], series["speed"])
            if v is not None and start <= e < end
        ]
        assert len(speeds) >= 3
        for v, b in speeds:
            assert math.isclose(v, b["distance"] / (b["step_ms"] / 1000), rel_tol=0.02), (v, b)
        assert max(v for v, _ in speeds) > 0.1
    # The panel names the week's distance beside the robot: the day's, all the history.
    text = page.inner_text(
        f'[data-testid="plot-robot"][data-robot="{robot}"] [data-testid="plot-driven"]'
    )
    assert text.endswith((" km", " m")), text
    value = float(text.split()[0]) * (1000 if text.endswith(" km") else 1)
    assert abs(value - raw) <= 0.02 * raw + 10, (text, raw)
    screenshot(page, "ui-plots-week.png")
    assert page.errors == []
