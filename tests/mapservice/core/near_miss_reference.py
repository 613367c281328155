"""The near-miss rule written plainly, tick by tick and pair by pair: what
mapservice/core/near_miss.py computes with arrays is checked against it."""

from __future__ import annotations

import bisect
import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

from mapservice.core.incident_model import Incident, IncidentThresholds, incident_id, mm2, pose_ref
from mapservice.core.ports import PoseRow


@dataclass(frozen=True)
class _Place:
    """A robot at a tick: where it was, how fast, and the poses around the tick."""

    x: float
    y: float
    moving: bool
    before: PoseRow
    after: PoseRow


def _places(track: Sequence[PoseRow], th: IncidentThresholds, from_tick: int) -> dict[int, _Place]:
    """The robot's position at every tick from `from_tick` on that its poses surround (not
    across a silence)."""
    places: dict[int, _Place] = {}
    first = max(0, bisect.bisect_left(track, from_tick, key=_ts) - 1)
    for a, b in zip(track[first:], track[first + 1 :], strict=False):
        gap = b.ts_ms - a.ts_ms
        if gap > th.offline_after_ms or b.ts_ms < from_tick:
            continue
        # faster than moving_m_s, in whole millimetres (mm/ms is m/s)
        moving = mm2(a, b) > (th.moving_m_s * gap) ** 2
        tick = max(-(-a.ts_ms // th.tick_ms), -(-from_tick // th.tick_ms)) * th.tick_ms
        while tick <= b.ts_ms:
            f = (tick - a.ts_ms) / gap
            places[tick] = _Place(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), moving, a, b)
            tick += th.tick_ms
    return places


def _ts(pose: PoseRow) -> int:
    return pose.ts_ms


def near_miss_incidents(
    tracks: dict[str, list[PoseRow]],
    th: IncidentThresholds,
    from_tick: int | None = None,
    involving: set[str] | None = None,
) -> list[Incident]:
    """The near misses over the ticks from `from_tick` on (all if None), of the pairs with a
    robot of `involving` (all if None)."""
    start_tick = -(10**18) if from_tick is None else from_tick
    at_tick: dict[int, list[tuple[str, _Place]]] = defaultdict(list)
    for robot, track in tracks.items():
        for tick, place in _places(track, th, start_tick).items():
            at_tick[tick].append((robot, place))
    # pair -> the ticks where they were too close, with their distance and places there
    close: dict[tuple[str, str], list[tuple[int, float, _Place, _Place]]] = defaultdict(list)
    cell = th.near_miss_m
    for tick in sorted(at_tick):
        grid: dict[tuple[int, int], list[tuple[str, _Place]]] = defaultdict(list)
        for robot, place in at_tick[tick]:
            grid[(math.floor(place.x / cell), math.floor(place.y / cell))].append((robot, place))
        for (cx, cy), members in grid.items():
            mine = [m for m in members if involving is None or m[0] in involving]
            if not mine:
                continue
            neighbours = [
                other
                for dx in (-1, 0, 1)
                for dy in (-1, 0, 1)
                for other in grid.get((cx + dx, cy + dy), ())
            ]
            for robot, place in mine:
                for other, there in neighbours:
                    # each pair once: from its first robot where both are of `involving`
                    if other == robot or (
                        other < robot and (involving is None or other in involving)
                    ):
                        continue
                    gap = math.hypot(place.x - there.x, place.y - there.y)
                    if gap < th.near_miss_m and (place.moving or there.moving):
                        if robot < other:
                            close[(robot, other)].append((tick, gap, place, there))
                        else:
                            close[(other, robot)].append((tick, gap, there, place))
    incidents = []
    for pair, ticks in sorted(close.items()):
        start = 0
        for i in range(1, len(ticks) + 1):
            if i < len(ticks) and ticks[i][0] - ticks[i - 1][0] == th.tick_ms:
                continue
            run = ticks[start:i]
            _, gap, place, there = min(run, key=lambda t: (t[1], t[0]))
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
                    x=(place.x + there.x) / 2,
                    y=(place.y + there.y) / 2,
                    severity="critical" if gap < th.near_miss_m / 2 else "warning",
                    measure=round(gap, 3),
                    evidence=tuple(
                        pose_ref(p) for p in (place.before, place.after, there.before, there.after)
                    ),
                    from_data_edge=any(run[0][0] - th.tick_ms < tracks[r][0].ts_ms for r in pair),
                )
            )
            start = i
    return incidents
