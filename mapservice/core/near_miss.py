"""The near-miss rule (mapservice/core/incidents.py states it) over arrays: every robot's
position at every tick at once, and the pairs closer than `near_miss_m` found by joining
the cells of a grid as wide as that distance, so that the live detection follows a fleet of
a thousand robots. The same figures as the rule written plainly (the tests compare them):
the same interpolation, in the same float operations, and the distances that decide
computed by `math.hypot` for the few candidate pairs.
"""

from __future__ import annotations

import bisect
import math
from operator import attrgetter
from typing import NamedTuple

import numpy as np

from mapservice.core.incident_model import Incident, IncidentThresholds, PoseRef, incident_id
from mapservice.core.ports import PoseRow


class Closest(NamedTuple):
    """A near miss's closest tick: the distance unrounded, then the tick (ordered as the
    rule picks: the closest, the earliest of equals)."""

    gap: float
    tick_ms: int


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
    sizes = np.fromiter(map(len, map(tracks.__getitem__, robots)), np.int64, len(robots))
    return PoseColumns(
        robots,
        np.repeat(np.arange(len(robots), dtype=np.int64), sizes),
        np.fromiter(map(attrgetter("ts_ms"), poses), np.int64, len(poses)),
        np.fromiter(map(attrgetter("x"), poses), np.float64, len(poses)),
        np.fromiter(map(attrgetter("y"), poses), np.float64, len(poses)),
    )


def with_tracks(cols: PoseColumns, tracks: dict[str, list[PoseRow]]) -> PoseColumns:
    """`cols` with the rows of the robots of `tracks` replaced by their poses there."""
    extra = pose_columns(tracks)
    if not extra.robots:
        return cols
    robots = cols.robots
    if not set(extra.robots).issubset(robots):
        robots = sorted(set(robots).union(extra.robots))
    place = {r: k for k, r in enumerate(robots)}
    own = np.asarray([place[r] for r in cols.robots], dtype=np.int64)[cols.robot]
    theirs = np.asarray([place[r] for r in extra.robots], dtype=np.int64)
    kept = ~np.isin(own, theirs)
    robot = np.concatenate((own[kept], theirs[extra.robot]))
    ts = np.concatenate((cols.ts[kept], extra.ts))
    order = np.lexsort((ts, robot))
    return PoseColumns(
        robots,
        robot[order],
        ts[order],
        np.concatenate((cols.x[kept], extra.x))[order],
        np.concatenate((cols.y[kept], extra.y))[order],
    )


def _bounds(cols: PoseColumns) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's first and last row."""
    sizes = np.bincount(cols.robot, minlength=len(cols.robots))
    first = np.cumsum(sizes) - sizes
    return first, first + sizes - 1


def _places(
    cols: PoseColumns, th: IncidentThresholds, from_tick: int | np.ndarray
) -> tuple[np.ndarray, ...]:
    """Every robot's places, one row per (robot, tick) its poses surround from `from_tick`
    on (one for all, or each robot's), all robots at once: per row its tick, robot index, x,
    y, whether it moved, and the rows of the poses before and after it."""
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
    firsts, seconds = [], []
    # From each place (in key order): the places of its cell and the next one up, then of
    # the three cells of the next column, each a run of consecutive keys.
    for low, high in ((0, 2), (height - 1, height + 2)):
        lo = np.searchsorted(sorted_key, sorted_key + low)
        counts = np.searchsorted(sorted_key, sorted_key + high) - lo
        total = int(counts.sum())
        if not total:
            continue
        firsts.append(np.repeat(np.arange(len(key)), counts))
        seconds.append(np.repeat(lo - (np.cumsum(counts) - counts), counts) + np.arange(total))
    if not firsts:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    i, j = order[np.concatenate(firsts)], order[np.concatenate(seconds)]
    # Two places in one cell are found from each of them: kept in robot order; in two
    # cells, from one of them only: put in robot order.
    once = (key[i] != key[j]) | (robot[i] < robot[j])
    i, j = i[once], j[once]
    i, j = np.where(robot[i] < robot[j], i, j), np.where(robot[i] < robot[j], j, i)
    near = (x[i] - x[j]) ** 2 + (y[i] - y[j]) ** 2 <= (cell * (1 + 1e-9)) ** 2
    keep = (robot[i] != robot[j]) & (mine[i] | mine[j]) & (moving[i] | moving[j]) & near
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
    closest: dict[str, Closest] | None = None,
) -> list[Incident]:
    """`near_miss_incidents` over columns. With `pairs_from`, the pairs it names each over
    the ticks from its own on, and for every pair its two robots' poses read as beginning
    with the newest before its first tick (as if each pair were judged alone, over the
    poses from that tick on: the live detection's runs that go on, in the same pass as the
    pairs from `from_tick`). `closest` is given each incident's closest tick, unrounded
    (what `join_runs` needs to carry a run on exactly)."""
    robots = cols.robots
    if not robots:
        return []
    everyone = from_tick if from_tick is not None else -(2**62)
    pair_from: dict[tuple[int, int], int] = {}
    for (a, b), ms in (pairs_from or {}).items():
        ra, rb = bisect.bisect_left(robots, a), bisect.bisect_left(robots, b)
        if max(ra, rb) < len(robots) and robots[ra] == a and robots[rb] == b:
            pair_from[(ra, rb)] = ms
    # each robot's first tick: the earliest of its named pairs', or from_tick
    robot_from = np.full(len(robots), everyone, dtype=np.int64)
    for (ra, rb), ms in pair_from.items():
        robot_from[ra] = min(robot_from[ra], ms)
        robot_from[rb] = min(robot_from[rb], ms)
    tick, robot, x, y, moving, before, after = _places(cols, th, robot_from)
    if not len(tick):
        return []
    # the robots whose pairs are judged (besides the named pairs): each one's flag
    chosen = None if involving is None else [r in involving for r in robots]
    if chosen is None:
        mine = np.ones(len(robot), dtype=bool)
    else:
        in_some = list(chosen)
        for ra, rb in pair_from:
            in_some[ra] = in_some[rb] = True
        mine = np.asarray(in_some)[robot]
    i, j = _close_pairs(tick, robot, x, y, moving, mine, th)
    # pair -> its close ticks: (tick, gap, the first robot's place row, the second's)
    close: dict[tuple[int, int], list[tuple[int, float, int, int]]] = {}
    candidates = zip(
        tick[i].tolist(),
        robot[i].tolist(),
        robot[j].tolist(),
        (x[i] - x[j]).tolist(),
        (y[i] - y[j]).tolist(),
        i.tolist(),
        j.tolist(),
        strict=True,
    )
    for t, ra, rb, dx, dy, a, b in sorted(candidates, key=lambda c: c[0]):
        named = pair_from.get((ra, rb))
        if named is not None:
            if t < named:
                continue
        elif t < everyone or (chosen is not None and not (chosen[ra] or chosen[rb])):
            continue
        gap = math.hypot(dx, dy)
        if gap < th.near_miss_m:
            close.setdefault((ra, rb), []).append((t, gap, a, b))
    # the runs: (pair, first tick, last tick, gap, the closest tick's place rows)
    runs: list[tuple[tuple[int, int], int, int, float, int, int]] = []
    for pair, ticks in sorted(close.items()):
        begin = 0
        for n in range(1, len(ticks) + 1):
            if n < len(ticks) and ticks[n][0] - ticks[n - 1][0] == th.tick_ms:
                continue
            run = ticks[begin:n]
            _, gap, a_row, b_row = min(run, key=lambda t: (t[1], t[0]))
            runs.append((pair, run[0][0], run[-1][0], gap, a_row, b_row))
            begin = n
    if not runs:
        return []
    # every run's figures from the arrays at once
    a_rows = np.array([run[4] for run in runs])
    b_rows = np.array([run[5] for run in runs])
    mid_x = ((x[a_rows] + x[b_rows]) / 2).tolist()
    mid_y = ((y[a_rows] + y[b_rows]) / 2).tolist()
    poses = np.stack((before[a_rows], after[a_rows], before[b_rows], after[b_rows]), axis=1)
    ev_robot, ev_ts = cols.robot[poses].tolist(), cols.ts[poses].tolist()
    ev_x, ev_y = cols.x[poses].tolist(), cols.y[poses].tolist()
    first, last = _bounds(cols)
    ts = cols.ts.tolist()
    newest = cols.ts[last].tolist()

    def first_ts(r: int, pair: tuple[int, int]) -> int:
        """The robot's first pose the pair's rule reads (with `pairs_from`: the newest
        before the pair's first tick)."""
        lo = int(first[r])
        if pairs_from is None:
            return int(ts[lo])
        at = bisect.bisect_left(ts, pair_from.get(pair, everyone), lo, int(last[r]) + 1) - 1
        return int(ts[max(at, lo)])

    incidents = []
    for k, (pair, start_ms, end_ms, gap, _, _) in enumerate(runs):
        names = (robots[pair[0]], robots[pair[1]])
        incidents.append(
            Incident(
                incident_id=incident_id("near_miss", names, start_ms),
                kind="near_miss",
                robots=names,
                start_ms=start_ms,
                end_ms=end_ms,
                # no later tick has both robots' positions yet
                ongoing=end_ms + th.tick_ms > min(newest[r] for r in pair),
                x=mid_x[k],
                y=mid_y[k],
                severity="critical" if gap < th.near_miss_m / 2 else "warning",
                measure=round(gap, 3),
                evidence=tuple(
                    PoseRef(robots[ev_robot[k][n]], ev_ts[k][n], ev_x[k][n], ev_y[k][n])
                    for n in range(4)
                ),
                from_data_edge=any(start_ms - th.tick_ms < first_ts(r, pair) for r in pair),
            )
        )
        if closest is not None:
            closest[incidents[-1].incident_id] = Closest(gap, int(tick[runs[k][4]]))
    return incidents
