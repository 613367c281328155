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


class _Places:
    """Every robot's places: one row per (robot, tick) its poses surround."""

    def __init__(self) -> None:
        self.tick: list[np.ndarray] = []
        self.robot: list[np.ndarray] = []
        self.x: list[np.ndarray] = []
        self.y: list[np.ndarray] = []
        self.moving: list[np.ndarray] = []
        self.before: list[np.ndarray] = []  # indexes into `poses`
        self.after: list[np.ndarray] = []
        self.poses: list[PoseRow] = []

    def add(self, k: int, track: list[PoseRow], th: IncidentThresholds, from_tick: int) -> None:
        n = len(track)
        if n < 2:
            return
        step = th.tick_ms
        ts = np.fromiter((p.ts_ms for p in track), np.int64, n)
        lo = max(-(-int(ts[0]) // step), -(-from_tick // step))
        hi = int(ts[-1]) // step
        if hi < lo:
            return
        xs = np.fromiter((p.x for p in track), np.float64, n)
        ys = np.fromiter((p.y for p in track), np.float64, n)
        ticks = np.arange(lo, hi + 1, dtype=np.int64) * step
        a = np.minimum(np.searchsorted(ts, ticks, side="right") - 1, n - 2)
        ok = ts[a + 1] - ts[a] <= th.offline_after_ms
        # A tick on a pose that a silence follows takes its place from the step before it.
        back = (~ok) & (ticks == ts[a]) & (a > 0)
        back &= ts[a] - ts[np.maximum(a - 1, 0)] <= th.offline_after_ms
        a = np.where(back, a - 1, a)
        keep = ok | back
        ticks, a = ticks[keep], a[keep]
        b = a + 1
        gap = ts[b] - ts[a]
        f = (ticks - ts[a]) / gap
        dx_mm = np.round((xs[a] - xs[b]) * 1000)
        dy_mm = np.round((ys[a] - ys[b]) * 1000)
        base = len(self.poses)
        self.poses += track
        self.tick.append(ticks)
        self.robot.append(np.full(len(ticks), k, dtype=np.int64))
        self.x.append(xs[a] + f * (xs[b] - xs[a]))
        self.y.append(ys[a] + f * (ys[b] - ys[a]))
        # faster than moving_m_s, in whole millimetres (mm/ms is m/s)
        self.moving.append(dx_mm * dx_mm + dy_mm * dy_mm > (th.moving_m_s * gap) ** 2)
        self.before.append(a + base)
        self.after.append(b + base)

    def arrays(self) -> tuple[np.ndarray, ...]:
        return tuple(
            np.concatenate(c)
            for c in (self.tick, self.robot, self.x, self.y, self.moving, self.before, self.after)
        )


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
    robots = sorted(tracks)
    places = _Places()
    start = -(2**62) if from_tick is None else from_tick
    for k, robot in enumerate(robots):
        places.add(k, tracks[robot], th, start)
    if not places.tick:
        return []
    tick, robot, x, y, moving, before, after = places.arrays()
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
    poses = places.poses
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
