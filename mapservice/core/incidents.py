"""Incidents: what went wrong on the floor, found from the robots' stored poses by pure rules,
so that the processors' live detection and a recomputation of any past span from the store
give the same incidents (same ids, same bounds).

Every rule reads one robot's poses in event-time order, one pose per instant (as the store
keeps them: `unique_poses` gives that order and that choice for any input order, with
duplicates). A rule's *condition* holds at some poses (or ticks); an incident is a maximal
run of consecutive poses where it holds, with no silence longer than `offline_after_ms`
inside the run (a silence is an incident of its own).

- **stuck**: at a pose with a planned path, every pose of the last `stuck_ms` (the window
  [t - stuck_ms, t]) lies less than `stuck_m` from it, and the robot reported throughout that
  window (its presence began at or before t - stuck_ms). The incident starts when the robot
  stopped: `stuck_ms` before the first pose where the condition held.
- **battery_low**: a pose that reports a level below `battery_low_percent` and is not
  charging. Levels are percent, as the simulator and VDA 5050 send them.
- **offline**: a silence longer than `offline_after_ms` between two poses: from the last pose
  before it to the first after it; or after the robot's newest pose, up to `until_ms` (the
  instant the history is known up to), which leaves it ongoing.
- **near_miss**: at ticks every `tick_ms` (absolute multiples, so every span is cut alike), each
  robot's position is interpolated between the two poses around the tick (not across a
  silence); two robots closer than `near_miss_m`, at least one of them moving faster than
  `moving_m_s` (its speed between those two poses), make the condition hold for the pair.

An incident's id is a digest of its kind, its robots and its start: the same incident found
twice (live, then recomputed; or before and after a restart) has the same id.
"""

from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import msgspec

from mapservice.core.ports import PoseRow

KINDS = ("near_miss", "stuck", "offline", "battery_low")
SEVERITIES = ("warning", "critical")


@dataclass(frozen=True)
class IncidentThresholds:
    """Where each rule draws its line (the settings' `MAPSERVICE_INCIDENT_*` values)."""

    near_miss_m: float = 1.0
    moving_m_s: float = 0.05
    stuck_m: float = 0.1
    stuck_ms: int = 30_000
    offline_after_ms: int = 10_000
    battery_low_percent: float = 15.0
    tick_ms: int = 500

    def __post_init__(self) -> None:
        for name in ("near_miss_m", "stuck_m", "battery_low_percent"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.moving_m_s < 0:
            raise ValueError("moving_m_s must not be negative")
        for name in ("stuck_ms", "offline_after_ms", "tick_ms"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive")

    @property
    def lookback_ms(self) -> int:
        """How far before a span a recomputation must read for the rules to see what they
        would have seen live: a stuck window and the silence that may precede it."""
        return self.stuck_ms + self.offline_after_ms


class PoseRef(msgspec.Struct, frozen=True, array_like=True):
    """A stored pose that made an incident (its evidence)."""

    robot_id: str
    ts_ms: int
    x: float
    y: float


class Incident(msgspec.Struct, frozen=True):
    incident_id: str
    kind: str
    robots: tuple[str, ...]
    start_ms: int
    end_ms: int
    # The condition still held at the newest pose known (or the silence lasts up to
    # `until_ms`): a later history may move its end.
    ongoing: bool
    x: float
    y: float
    severity: str
    # The kind's own figure: the closest distance in metres (near_miss), the seconds stopped
    # (stuck) or silent (offline), the lowest level in percent (battery_low).
    measure: float
    evidence: tuple[PoseRef, ...]
    # The run began at the first pose the rule was given: it may reach further back than the
    # history read (a recomputation reads further back for these).
    from_data_edge: bool = False


def incident_id(kind: str, robots: Sequence[str], start_ms: int) -> str:
    key = "\x1f".join((kind, *robots, str(start_ms)))
    return hashlib.blake2b(key.encode(), digest_size=16).hexdigest()


def unique_poses(poses: Iterable[PoseRow]) -> dict[str, list[PoseRow]]:
    """Each robot's poses in event-time order, one per instant: of several poses of one
    robot at one instant (a redelivery, or a robot that sent two), the last given, as the
    store keeps the last written."""
    by_robot: dict[str, dict[int, PoseRow]] = defaultdict(dict)
    for pose in poses:
        by_robot[pose.robot_id][pose.ts_ms] = pose
    return {robot: [at[ts] for ts in sorted(at)] for robot, at in sorted(by_robot.items())}


def detect(
    poses: Iterable[PoseRow], until_ms: int, thresholds: IncidentThresholds | None = None
) -> list[Incident]:
    """Every incident the rules find in `poses` (any order, duplicates allowed), the history
    being known up to `until_ms`; sorted by start, kind and robots."""
    th = thresholds or IncidentThresholds()
    tracks = unique_poses(pose for pose in poses if pose.ts_ms <= until_ms)
    found: list[Incident] = []
    for track in tracks.values():
        found += stuck_incidents(track, th)
        found += battery_low_incidents(track, th)
        found += offline_incidents(track, until_ms, th)
    found += near_miss_incidents(tracks, th)
    found.sort(key=lambda i: (i.start_ms, i.kind, i.robots))
    return found


def _presences(track: Sequence[PoseRow], offline_after_ms: int) -> list[tuple[int, int]]:
    """[first, last] indexes of the runs of poses with no silence over `offline_after_ms`."""
    runs: list[tuple[int, int]] = []
    start = 0
    for i in range(1, len(track)):
        if track[i].ts_ms - track[i - 1].ts_ms > offline_after_ms:
            runs.append((start, i - 1))
            start = i
    if track:
        runs.append((start, len(track) - 1))
    return runs


def _runs(flags: Sequence[bool], presences: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """[first, last] indexes of the maximal runs of true flags inside each presence."""
    runs: list[tuple[int, int]] = []
    for first, last in presences:
        start: int | None = None
        for i in range(first, last + 1):
            if flags[i] and start is None:
                start = i
            elif not flags[i] and start is not None:
                runs.append((start, i - 1))
                start = None
        if start is not None:
            runs.append((start, last))
    return runs


def _ref(pose: PoseRow) -> PoseRef:
    return PoseRef(pose.robot_id, pose.ts_ms, pose.x, pose.y)


def _distance(a: PoseRow, b: PoseRow) -> float:
    return math.hypot(a.x - b.x, a.y - b.y)


def _mm2(a: PoseRow, b: PoseRow) -> int:
    """The squared distance in whole millimetres (positions are stored to the millimetre):
    exact, so a robot that moved exactly the threshold is judged alike on every machine."""
    dx, dy = round((a.x - b.x) * 1000), round((a.y - b.y) * 1000)
    return dx * dx + dy * dy


def stuck_incidents(track: Sequence[PoseRow], th: IncidentThresholds) -> list[Incident]:
    presences = _presences(track, th.offline_after_ms)
    limit_mm2 = (th.stuck_m * 1000) ** 2
    flags = [False] * len(track)
    for first, last in presences:
        oldest = first  # the oldest pose of the window ending at i
        for i in range(first, last + 1):
            pose = track[i]
            while track[oldest].ts_ms < pose.ts_ms - th.stuck_ms:
                oldest += 1
            flags[i] = (
                bool(pose.path)
                and track[first].ts_ms <= pose.ts_ms - th.stuck_ms
                and all(_mm2(track[j], pose) < limit_mm2 for j in range(oldest, i))
            )
    first_judged = next(
        (
            i
            for i in range(presences[0][1] + 1 if presences else 0)
            if track[i].ts_ms - th.stuck_ms >= track[0].ts_ms
        ),
        -1,
    )
    incidents = []
    for a, b in _runs(flags, presences):
        start_ms = track[a].ts_ms - th.stuck_ms
        still_s = (track[b].ts_ms - start_ms) / 1000
        robot = track[a].robot_id
        incidents.append(
            Incident(
                incident_id=incident_id("stuck", (robot,), start_ms),
                kind="stuck",
                robots=(robot,),
                start_ms=start_ms,
                end_ms=track[b].ts_ms,
                ongoing=b == len(track) - 1,
                x=track[b].x,
                y=track[b].y,
                severity="critical" if still_s >= 300 else "warning",
                measure=still_s,
                evidence=(_ref(track[a]), _ref(track[b])),
                # the first pose whose window the loaded history covers: it may have
                # stood still for longer
                from_data_edge=a == first_judged,
            )
        )
    return incidents


def is_charging(value: bool | str | None) -> bool:
    """The 2019 contract's `charging` as sent: a flag, or a word some robots send for it."""
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes", "charging")
    return bool(value)


def battery_low_incidents(track: Sequence[PoseRow], th: IncidentThresholds) -> list[Incident]:
    flags = [
        p.battery_level is not None
        and p.battery_level < th.battery_low_percent
        and not is_charging(p.charging)
        for p in track
    ]
    incidents = []
    for a, b in _runs(flags, _presences(track, th.offline_after_ms)):
        run = track[a : b + 1]
        lowest = min(run, key=lambda p: (p.battery_level, p.ts_ms))
        level = float(lowest.battery_level or 0.0)
        robot = track[a].robot_id
        incidents.append(
            Incident(
                incident_id=incident_id("battery_low", (robot,), track[a].ts_ms),
                kind="battery_low",
                robots=(robot,),
                start_ms=track[a].ts_ms,
                end_ms=track[b].ts_ms,
                ongoing=b == len(track) - 1,
                x=lowest.x,
                y=lowest.y,
                severity="critical" if level < th.battery_low_percent / 3 else "warning",
                measure=level,
                evidence=(_ref(track[a]), _ref(lowest)),
                from_data_edge=a == 0,
            )
        )
    return incidents


def offline_incidents(
    track: Sequence[PoseRow], until_ms: int, th: IncidentThresholds
) -> list[Incident]:
    silences: list[tuple[PoseRow, PoseRow | None, int, bool]] = [
        (track[i], track[i + 1], track[i + 1].ts_ms, False)
        for i in range(len(track) - 1)
        if track[i + 1].ts_ms - track[i].ts_ms > th.offline_after_ms
    ]
    if track and until_ms - track[-1].ts_ms > th.offline_after_ms:
        silences.append((track[-1], None, until_ms, True))
    incidents = []
    for before, after, end_ms, ongoing in silences:
        silent_s = (end_ms - before.ts_ms) / 1000
        evidence = (_ref(before),) if after is None else (_ref(before), _ref(after))
        incidents.append(
            Incident(
                incident_id=incident_id("offline", (before.robot_id,), before.ts_ms),
                kind="offline",
                robots=(before.robot_id,),
                start_ms=before.ts_ms,
                end_ms=end_ms,
                ongoing=ongoing,
                x=before.x,
                y=before.y,
                severity="critical" if silent_s >= 300 else "warning",
                measure=silent_s,
                evidence=evidence,
            )
        )
    return incidents


@dataclass(frozen=True)
class _Place:
    """A robot at a tick: where it was, how fast, and the poses around the tick."""

    x: float
    y: float
    moving: bool
    before: PoseRow
    after: PoseRow


def _places(track: Sequence[PoseRow], th: IncidentThresholds) -> dict[int, _Place]:
    """The robot's position at every tick its poses surround (not across a silence)."""
    places: dict[int, _Place] = {}
    for a, b in zip(track, track[1:], strict=False):
        gap = b.ts_ms - a.ts_ms
        if gap > th.offline_after_ms:
            continue
        # faster than moving_m_s, in whole millimetres (mm/ms is m/s)
        moving = _mm2(a, b) > (th.moving_m_s * gap) ** 2
        tick = -(-a.ts_ms // th.tick_ms) * th.tick_ms
        while tick <= b.ts_ms:
            f = (tick - a.ts_ms) / gap
            places[tick] = _Place(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), moving, a, b)
            tick += th.tick_ms
    return places


def near_miss_incidents(tracks: dict[str, list[PoseRow]], th: IncidentThresholds) -> list[Incident]:
    at_tick: dict[int, list[tuple[str, _Place]]] = defaultdict(list)
    for robot, track in tracks.items():
        for tick, place in _places(track, th).items():
            at_tick[tick].append((robot, place))
    # pair -> the ticks where they were too close, with their distance and places there
    close: dict[tuple[str, str], list[tuple[int, float, _Place, _Place]]] = defaultdict(list)
    cell = th.near_miss_m
    for tick in sorted(at_tick):
        grid: dict[tuple[int, int], list[tuple[str, _Place]]] = defaultdict(list)
        for robot, place in at_tick[tick]:
            grid[(math.floor(place.x / cell), math.floor(place.y / cell))].append((robot, place))
        for (cx, cy), members in grid.items():
            neighbours = [
                other
                for dx in (-1, 0, 1)
                for dy in (-1, 0, 1)
                for other in grid.get((cx + dx, cy + dy), ())
            ]
            for robot, place in members:
                for other, there in neighbours:
                    if other <= robot:
                        continue
                    gap = math.hypot(place.x - there.x, place.y - there.y)
                    if gap < th.near_miss_m and (place.moving or there.moving):
                        close[(robot, other)].append((tick, gap, place, there))
    incidents = []
    for pair, ticks in sorted(close.items()):
        start = 0
        for i in range(1, len(ticks) + 1):
            if i < len(ticks) and ticks[i][0] - ticks[i - 1][0] == th.tick_ms:
                continue
            run = ticks[start:i]
            tick, gap, place, there = min(run, key=lambda t: (t[1], t[0]))
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
                        _ref(p) for p in (place.before, place.after, there.before, there.after)
                    ),
                    from_data_edge=any(run[0][0] - th.tick_ms < tracks[r][0].ts_ms for r in pair),
                )
            )
            start = i
    return incidents
