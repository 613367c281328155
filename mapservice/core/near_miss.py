"""The near-miss rule (mapservice/core/incidents.py states it) over arrays: every robot's
position at every tick at once, and the pairs closer than `near_miss_m` found by joining
the cells of a grid as wide as that distance, so that the live detection follows a fleet of
a thousand robots. The same figures as the rule written plainly (the tests compare them):
the same interpolation, in the same float operations, and the distances that decide
computed by `math.hypot` for the few candidate pairs.
"""

from __future__ import annotations

import math

import numpy as np

from mapservice.core.incident_model import Incident, IncidentThresholds, incident_id, pose_ref
from mapservice.core.ports import PoseRow

# the 3x3 cells around one: a pair closer than the cell size lies in neighbouring cells
_NEIGHBOURS = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]


def _places(
    tracks: dict[str, list[PoseRow]], robots: list[str], th: IncidentThresholds, from_tick: int
) -> tuple[list[PoseRow], tuple[np.ndarray, ...]]:
    """Every robot's places, one row per (robot, tick) its poses surround, all robots at
    once: (the poses, flat; and per row its tick, robot index, x, y, whether it moved, and
    the indexes of the poses before and after it)."""
    step, off = th.tick_ms, th.offline_after_ms
    poses = [p for r in robots for p in tracks[r]]
    sizes = np.fromiter((len(tracks[r]) for r in robots), np.int64, len(robots))
    first = np.cumsum(sizes) - sizes
    ts = np.fromiter((p.ts_ms for p in poses), np.int64, len(poses))
    xs = np.fromiter((p.x for p in poses), np.float64, len(poses))
    ys = np.fromiter((p.y for p in poses), np.float64, len(poses))
    has = sizes >= 2
    last = first + sizes - 1
    lo = np.maximum(-(-ts[np.minimum(first, len(ts) - 1)] // step), -(-from_tick // step))
    hi = ts[last] // step
    counts = np.where(has, np.maximum(hi - lo + 1, 0), 0)
    total = int(counts.sum())
    robot = np.repeat(np.arange(len(robots), dtype=np.int64), counts)
    ticks = (
        np.repeat(lo, counts) + np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    ) * step
    # One sorted key for every robot's poses: its index, then the time.
    span = int(ts.max()) + 1 if len(ts) else 1
    keys = np.repeat(np.arange(len(robots), dtype=np.int64), sizes) * span + ts
    a = np.searchsorted(keys, robot * span + ticks, side="right") - 1
    a = np.minimum(a, last[robot] - 1)
    ok = ts[a + 1] - ts[a] <= off
    # A tick on a pose that a silence follows takes its place from the step before it.
    back = (~ok) & (ticks == ts[a]) & (a > first[robot])
    back &= ts[a] - ts[np.maximum(a - 1, 0)] <= off
    a = np.where(back, a - 1, a)
    keep = ok | back
    ticks, robot, a = ticks[keep], robot[keep], a[keep]
    b = a + 1
    gap = ts[b] - ts[a]
    f = (ticks - ts[a]) / gap
    dx_mm = np.round((xs[a] - xs[b]) * 1000)
    dy_mm = np.round((ys[a] - ys[b]) * 1000)
    # faster than moving_m_s, in whole millimetres (mm/ms is m/s)
    moving = dx_mm * dx_mm + dy_mm * dy_mm > (th.moving_m_s * gap) ** 2
    x = xs[a] + f * (xs[b] - xs[a])
    y = ys[a] + f * (ys[b] - ys[a])
    return poses, (ticks, robot, x, y, moving, a, b)


def _close_pairs(
    tick: np.ndarray,
    robot: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    moving: np.ndarray,
    mine: np.ndarray,
    th: IncidentThresholds,
) -> tuple[np.ndarray, np.ndarray]:
    """Row indexes (i, j) of the places at one tick of two robots (robot[i] < robot[j], one
    of them `mine`) in neighbouring cells, at most a hair over `near_miss_m` apart, one moving."""
    cell = th.near_miss_m
    cx = np.floor(x / cell).astype(np.int64)
    cy = np.floor(y / cell).astype(np.int64)
    ti = (tick - tick.min()) // th.tick_ms
    cx -= cx.min() - 1
    cy -= cy.min() - 1
    width, height = int(cx.max()) + 2, int(cy.max()) + 2
    key = (ti * width + cx) * height + cy
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    firsts, seconds = [], []
    for dx, dy in _NEIGHBOURS:
        wanted = key + dx * height + dy
        lo = np.searchsorted(sorted_key, wanted, side="left")
        counts = np.searchsorted(sorted_key, wanted, side="right") - lo
        total = int(counts.sum())
        if not total:
            continue
        i = np.repeat(np.arange(len(key)), counts)
        starts = np.repeat(np.cumsum(counts) - counts, counts)
        j = order[np.repeat(lo, counts) + np.arange(total) - starts]
        firsts.append(i)
        seconds.append(j)
    if not firsts:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    i, j = np.concatenate(firsts), np.concatenate(seconds)
    near = (x[i] - x[j]) ** 2 + (y[i] - y[j]) ** 2 <= (cell * (1 + 1e-9)) ** 2
    keep = (robot[i] < robot[j]) & (mine[i] | mine[j]) & (moving[i] | moving[j]) & near
    return i[keep], j[keep]


def near_miss_incidents(
    tracks: dict[str, list[PoseRow]],
    th: IncidentThresholds,
    from_tick: int | None = None,
    involving: set[str] | None = None,
) -> list[Incident]:
    """The near misses over the ticks from `from_tick` on (all if None), of the pairs with a
    robot of `involving` (all if None)."""
    robots = sorted(r for r, track in tracks.items() if track)
    if not robots:
        return []
    start = -(2**62) if from_tick is None else from_tick
    poses, (tick, robot, x, y, moving, before, after) = _places(tracks, robots, th, start)
    if not len(tick):
        return []
    mine = (
        np.ones(len(robot), dtype=bool)
        if involving is None
        else np.isin(robot, [k for k, r in enumerate(robots) if r in involving])
    )
    i, j = _close_pairs(tick, robot, x, y, moving, mine, th)
    # pair -> its close ticks: (tick, gap, the first robot's row, the second's)
    close: dict[tuple[str, str], list[tuple[int, float, int, int]]] = {}
    for a, b in sorted(zip(i.tolist(), j.tolist(), strict=True), key=lambda ab: tick[ab[0]]):
        gap = math.hypot(x[a] - x[b], y[a] - y[b])
        if gap < th.near_miss_m:
            pair = (robots[robot[a]], robots[robot[b]])
            close.setdefault(pair, []).append((int(tick[a]), gap, a, b))
    incidents = []
    for pair, ticks in sorted(close.items()):
        first = 0
        for n in range(1, len(ticks) + 1):
            if n < len(ticks) and ticks[n][0] - ticks[n - 1][0] == th.tick_ms:
                continue
            run = ticks[first:n]
            _, gap, a, b = min(run, key=lambda t: (t[1], t[0]))
            start_ms = run[0][0]
            incidents.append(
                Incident(
                    incident_id=incident_id("near_miss", pair, start_ms),
                    kind="near_miss",
                    robots=pair,
                    start_ms=start_ms,
                    end_ms=run[-1][0],
                    # no later tick has both robots' positions yet
                    ongoing=run[-1][0] + th.tick_ms > min(tracks[r][-1].ts_ms for r in pair),
                    x=(float(x[a]) + float(x[b])) / 2,
                    y=(float(y[a]) + float(y[b])) / 2,
                    severity="critical" if gap < th.near_miss_m / 2 else "warning",
                    measure=round(gap, 3),
                    evidence=tuple(
                        pose_ref(poses[int(k)]) for k in (before[a], after[a], before[b], after[b])
                    ),
                    from_data_edge=any(run[0][0] - th.tick_ms < tracks[r][0].ts_ms for r in pair),
                )
            )
            first = n
    return incidents
