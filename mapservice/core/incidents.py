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

from collections import defaultdict
from collections.abc import Iterable, Sequence

from mapservice.core.incident_model import (
    KINDS,
    OFFLINE_CRITICAL_S,
    SEVERITIES,
    STUCK_CRITICAL_S,
    Incident,
    IncidentThresholds,
    PoseRef,
    incident_id,
    mm2,
    pose_ref,
)
from mapservice.core.near_miss import near_miss_incidents
from mapservice.core.ports import PoseRow

__all__ = [
    "KINDS",
    "SEVERITIES",
    "Incident",
    "IncidentThresholds",
    "PoseRef",
    "battery_low_at",
    "battery_low_incidents",
    "detect",
    "flag_runs",
    "incident_id",
    "is_charging",
    "near_miss_incidents",
    "offline_incidents",
    "presence_runs",
    "stuck_incidents",
    "stuck_possible_at",
    "unique_poses",
]


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


def presence_runs(track: Sequence[PoseRow], offline_after_ms: int) -> list[tuple[int, int]]:
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


def flag_runs(flags: Sequence[bool], presences: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
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


def stuck_possible_at(previous: PoseRow | None, pose: PoseRow, th: IncidentThresholds) -> bool:
    """Whether the stuck condition can hold at `pose`, judged from the pose before it in its
    presence only (`previous`, None if it opens one): it needs a planned path, and the pose
    before, when inside the window, nearer than `stuck_m`. The condition's first part, so
    that the live detection can pass over a moving robot without its window."""
    if not pose.path:
        return False
    if previous is None or previous.ts_ms < pose.ts_ms - th.stuck_ms:
        return True
    # A difference along one axis of at least stuck_m and half a millimetre rounds to
    # stuck_m or more (mm2's rounding moves it by half a millimetre at most): far enough.
    reach = th.stuck_m * 1000 + 0.5
    dx, dy = (previous.x - pose.x) * 1000, (previous.y - pose.y) * 1000
    if dx >= reach or -dx >= reach or dy >= reach or -dy >= reach:
        return False
    return mm2(previous, pose) < (th.stuck_m * 1000) ** 2


def stuck_incidents(
    track: Sequence[PoseRow], th: IncidentThresholds, judged_from_ms: int | None = None
) -> list[Incident]:
    """`judged_from_ms`: the condition is judged at the poses from then on only (the
    earlier ones are only looked back on), for a caller that knows the runs before."""
    presences = presence_runs(track, th.offline_after_ms)
    limit_mm2 = (th.stuck_m * 1000) ** 2  # as stuck_possible_at
    flags = [False] * len(track)
    for first, last in presences:
        oldest = first  # the oldest pose of the window ending at i
        for i in range(first, last + 1):
            pose = track[i]
            if judged_from_ms is not None and pose.ts_ms < judged_from_ms:
                continue
            if not stuck_possible_at(track[i - 1] if i > first else None, pose, th):
                continue
            while track[oldest].ts_ms < pose.ts_ms - th.stuck_ms:
                oldest += 1
            flags[i] = track[first].ts_ms <= pose.ts_ms - th.stuck_ms and all(
                mm2(track[j], pose) < limit_mm2 for j in range(oldest, i)
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
    for a, b in flag_runs(flags, presences):
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
                severity="critical" if still_s >= STUCK_CRITICAL_S else "warning",
                measure=still_s,
                evidence=(pose_ref(track[a]), pose_ref(track[b])),
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


def battery_low_at(pose: PoseRow, th: IncidentThresholds) -> bool:
    """The battery_low condition at one pose."""
    return (
        pose.battery_level is not None
        and pose.battery_level < th.battery_low_percent
        and not is_charging(pose.charging)
    )


def battery_low_incidents(track: Sequence[PoseRow], th: IncidentThresholds) -> list[Incident]:
    flags = [battery_low_at(p, th) for p in track]
    incidents = []
    for a, b in flag_runs(flags, presence_runs(track, th.offline_after_ms)):
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
                evidence=(pose_ref(track[a]), pose_ref(lowest)),
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
        evidence = (pose_ref(before),) if after is None else (pose_ref(before), pose_ref(after))
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
                severity="critical" if silent_s >= OFFLINE_CRITICAL_S else "warning",
                measure=silent_s,
                evidence=evidence,
            )
        )
    return incidents
