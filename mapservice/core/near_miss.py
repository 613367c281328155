"""The near-miss rule (mapservice/core/incidents.py states it) over arrays: every robot's
position at every tick at once, and the pairs closer than `near_miss_m` found by joining
the cells of a grid as wide as that distance, so that the live detection follows a fleet of
a thousand robots. The same figures as the rule written plainly (the tests compare them):
the same interpolation, in the same float operations, and the distances that decide
computed by `math.hypot` for the few candidate pairs.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from mapservice.core.incident_model import Incident, IncidentThresholds, PoseRef, incident_id
from mapservice.core.ports import PoseRow

# A pair closer than the cell size lies in one cell or two neighbouring ones: each cell
# looks at itself and at four of its eight neighbours, so that of two neighbours one looks
# at the other.
_LOOKED_AT = [(0, 0), (0, 1), (1, -1), (1, 0), (1, 1)]


class PoseColumns(NamedTuple):
    """Robots' poses as columns, sorted by robot, then time, one pose per instant."""

    robots: list[str]  # sorted; `robot` indexes it
    robot: np.ndarray
    ts: np.ndarray
    x: np.ndarray
    y: np.ndarray


def pose_columns(tracks: dict[str, list[PoseRow]]) -> PoseColumns:
    robots = sorted(r for r, track in tracks.items() if track)
    poses = [p for r in robots for p in tracks[r]]
    sizes = np.fromiter((len(tracks[r]) for r in robots), np.int64, len(robots))
    return PoseColumns(
        robots,
        np.repeat(np.arange(len(robots), dtype=np.int64), sizes),
        np.fromiter((p.ts_ms for p in poses), np.int64, len(poses)),
        np.fromiter((p.x for p in poses), np.float64, len(poses)),
        np.fromiter((p.y for p in poses), np.float64, len(poses)),
    )


def _bounds(cols: PoseColumns) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's first and last row."""
    sizes = np.bincount(cols.robot, minlength=len(cols.robots))
    first = np.cumsum(sizes) - sizes
    return first, first + sizes - 1


def _places(cols: PoseColumns, th: IncidentThresholds, from_tick: int) -> tuple[np.ndarray, ...]:
    """Every robot's places, one row per (robot, tick) its poses surround, all robots at
    once: per row its tick, robot index, x, y, whether it moved, and the rows of the poses
    before and after it."""
    step, off = th.tick_ms, th.offline_after_ms
    ts, xs, ys = cols.ts, cols.x, cols.y
    first, last = _bounds(cols)
    sizes = last - first + 1
    has = sizes >= 2
    lo = np.maximum(-(-ts[np.minimum(first, len(ts) - 1)] // step), -(-from_tick // step))
    hi = ts[np.maximum(last, 0)] // step
    counts = np.where(has, np.maximum(hi - lo + 1, 0), 0)
    total = int(counts.sum())
    robot = np.repeat(np.arange(len(cols.robots), dtype=np.int64), counts)
    ticks = (
        np.repeat(lo, counts) + np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    ) * step
    # One sorted key for every robot's poses: its index, then the time.
    span = int(ts.max()) + 1 if len(ts) else 1
    keys = cols.robot * span + ts
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
    return ticks, robot, x, y, moving, a, b


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
    # the occupied cells: each one's key, where its places begin in `order`, how many
    begins = np.flatnonzero(np.concatenate(([True], sorted_key[1:] != sorted_key[:-1])))
    cells = sorted_key[begins]
    sizes = np.diff(np.append(begins, len(key)))
    firsts, seconds = [], []
    for dx, dy in _LOOKED_AT:
        wanted = key + dx * height + dy
        at = np.minimum(np.searchsorted(cells, wanted), len(cells) - 1)
        counts = np.where(cells[at] == wanted, sizes[at], 0)
        total = int(counts.sum())
        if not total:
            continue
        i = np.repeat(np.arange(len(key)), counts)
        starts = np.repeat(np.cumsum(counts) - counts, counts)
        j = order[np.repeat(begins[at], counts) + np.arange(total) - starts]
        if (dx, dy) != (0, 0):  # found from one of the two cells only: in robot order
            i, j = np.where(robot[i] < robot[j], i, j), np.where(robot[i] < robot[j], j, i)
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
    return near_misses(pose_columns(tracks), th, from_tick, involving)


def near_misses(
    cols: PoseColumns,
    th: IncidentThresholds,
    from_tick: int | None = None,
    involving: set[str] | None = None,
    pairs_from: dict[tuple[str, str], int] | None = None,
) -> list[Incident]:
    """`near_miss_incidents` over columns. With `pairs_from`, of those pairs only, each
    over the ticks from its own instant on, as if its two robots' poses began with the
    newest before that instant (several pairs' runs in one pass)."""
    robots = cols.robots
    if not robots:
        return []
    if pairs_from is not None:
        if not pairs_from:
            return []
        from_tick = min(pairs_from.values())
        involving = {r for pair in pairs_from for r in pair}
    start = -(2**62) if from_tick is None else from_tick
    tick, robot, x, y, moving, before, after = _places(cols, th, start)
    if not len(tick):
        return []
    mine = (
        np.ones(len(robot), dtype=bool)
        if involving is None
        else np.isin(robot, [k for k, r in enumerate(robots) if r in involving])
    )
    i, j = _close_pairs(tick, robot, x, y, moving, mine, th)
    first, last = _bounds(cols)
    ts = cols.ts

    def ref(row: int) -> PoseRef:
        return PoseRef(
            robots[int(cols.robot[row])], int(ts[row]), float(cols.x[row]), float(cols.y[row])
        )

    def first_ts(r: int, pair: tuple[str, str]) -> int:
        """The robot's first pose the pair's rule reads: the newest before its instant."""
        if pairs_from is None:
            return int(ts[first[r]])
        lo, hi = int(first[r]), int(last[r]) + 1
        at = lo + int(np.searchsorted(ts[lo:hi], pairs_from[pair], side="left")) - 1
        return int(ts[max(at, lo)])

    # pair -> its close ticks: (tick, gap, the first robot's row, the second's)
    close: dict[tuple[str, str], list[tuple[int, float, int, int]]] = {}
    for a, b in sorted(zip(i.tolist(), j.tolist(), strict=True), key=lambda ab: tick[ab[0]]):
        pair = (robots[robot[a]], robots[robot[b]])
        if pairs_from is not None and tick[a] < pairs_from.get(pair, 2**62):
            continue
        gap = math.hypot(x[a] - x[b], y[a] - y[b])
        if gap < th.near_miss_m:
            close.setdefault(pair, []).append((int(tick[a]), gap, a, b))
    incidents = []
    for pair, ticks in sorted(close.items()):
        pair_rows = (int(robot[ticks[0][2]]), int(robot[ticks[0][3]]))
        begin = 0
        for n in range(1, len(ticks) + 1):
            if n < len(ticks) and ticks[n][0] - ticks[n - 1][0] == th.tick_ms:
                continue
            run = ticks[begin:n]
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
                    ongoing=run[-1][0] + th.tick_ms > min(int(ts[last[r]]) for r in pair_rows),
                    x=(float(x[a]) + float(x[b])) / 2,
                    y=(float(y[a]) + float(y[b])) / 2,
                    severity="critical" if gap < th.near_miss_m / 2 else "warning",
                    measure=round(gap, 3),
                    evidence=tuple(ref(int(k)) for k in (before[a], after[a], before[b], after[b])),
                    from_data_edge=any(
                        run[0][0] - th.tick_ms < first_ts(r, pair) for r in pair_rows
                    ),
                )
            )
            begin = n
    return incidents
