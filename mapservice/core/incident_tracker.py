"""Live detection of incidents: each robot's recent poses in memory and the incidents found
so far; on every stored batch the rules (incidents.py) run again over the part of the
history the batch can change, and what they find there replaces what was found before.
So the incidents found live, batch by batch, whatever order the poses came in (late ones,
redelivered ones, across restarts), are the ones a recomputation of the stored history
finds: the same ids, bounds and evidence.

What a batch can change, for poses of robots R from instant `a` on:
- a robot's own incidents (stuck, battery_low, offline) that end at or after
  a - offline_after_ms (a run before that is separated from `a` by a silence, or ends at
  a pose before it whose window the batch does not reach), or are ongoing;
- the near misses of pairs with a robot of R that end at or after a - offline_after_ms -
  tick_ms (a tick's positions come from the poses around it, never across a silence), or
  are ongoing.
The rules re-run from `lookback_ms` before that; a run that reaches back to where they
started (`from_data_edge`) is run again from further back, from memory or the store.

An ongoing silence (`offline`) grows with the clock, not with batches: `tick` finds robots
that fell silent; its end and length are refreshed when it ends or turns critical, not on
every tick (the stored row says when it was last found; readers extend an ongoing one to now).
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterable, Sequence

import msgspec

from mapservice.core.incidents import (
    Incident,
    IncidentThresholds,
    battery_low_incidents,
    near_miss_incidents,
    offline_incidents,
    stuck_incidents,
    unique_poses,
)
from mapservice.core.ports import PoseRow

# A robot's own incidents; a near miss involves two.
OWN_KINDS = ("stuck", "battery_low", "offline")
# (from_ms, to_ms, robot_id or None for every robot) -> the stored poses in [from, to),
# and each robot's newest before from_ms
ReadPoses = Callable[[int, int, str | None], list[PoseRow]]
# (from_ms, to_ms) -> the stored incidents meeting [from, to)
ReadIncidents = Callable[[int, int], list[Incident]]


def _key(incident: Incident) -> Incident:
    """What a new finding must differ in to be written again: all but an ongoing silence's
    end and length, which grow with the clock."""
    if incident.kind == "offline" and incident.ongoing:
        return msgspec.structs.replace(incident, end_ms=0, measure=0.0)
    return incident


def _ts(pose: PoseRow) -> int:
    return pose.ts_ms


class IncidentTracker:
    def __init__(
        self,
        read: ReadPoses,
        read_incidents: ReadIncidents,
        thresholds: IncidentThresholds | None = None,
        keep_ms: int = 300_000,
    ) -> None:
        self.read = read
        self.read_incidents = read_incidents
        self.th = thresholds or IncidentThresholds()
        self.keep_ms = keep_ms
        self.tracks: dict[str, list[PoseRow]] = {}
        # A robot's track holds every stored pose of it at or after its instant here (this
        # default for robots not named; and before it, the robot's newest); earlier ones
        # are read from the store.
        self.held_from_ms = 0
        self.held_from: dict[str, int] = {}
        # By id, the latest finding of each incident that is ongoing or ended at or after
        # `current_from_ms`; the earlier ones are read from the store.
        self.current: dict[str, Incident] = {}
        self.current_from_ms = 0
        self.found: dict[str, Incident] = {}  # new or changed findings, not taken yet
        self.retracted: dict[str, Incident] = {}

    # --- state --------------------------------------------------------------------------

    def load(
        self, poses: Iterable[PoseRow], held_from_ms: int, stored: Sequence[Incident], now_ms: int
    ) -> None:
        """Starts from the stored history: `poses` every stored pose from `held_from_ms` on
        (and each robot's newest before it), `stored` the incidents stored that meet that
        span. The rules then run over it, for what was stored but not yet found."""
        self.tracks = unique_poses(poses)
        self.held_from_ms = held_from_ms
        self.held_from = {}
        self.current = {i.incident_id: i for i in stored}
        self.current_from_ms = held_from_ms - self.th.lookback_ms
        self.found.clear()
        self.retracted.clear()
        if self.tracks:
            self._redo(set(self.tracks), held_from_ms, now_ms)

    def add(self, poses: Sequence[PoseRow], now_ms: int) -> None:
        """A stored batch's poses (as the store keeps them, in the order stored)."""
        if not poses:
            return
        robots: set[str] = set()
        for pose in poses:
            robots.add(pose.robot_id)
            track = self.tracks.setdefault(pose.robot_id, [])
            at = bisect.bisect_left(track, pose.ts_ms, key=_ts)
            if at < len(track) and track[at].ts_ms == pose.ts_ms:
                track[at] = pose  # the store keeps the last written
            else:
                track.insert(at, pose)
        self._redo(robots, min(p.ts_ms for p in poses), now_ms)

    def tick(self, now_ms: int) -> None:
        """Silences that began or turned critical as the clock moved."""
        for track in self.tracks.values():
            if not track or now_ms - track[-1].ts_ms <= self.th.offline_after_ms:
                continue
            for incident in offline_incidents(track[-1:], now_ms, self.th):
                self._note(incident)

    def take(self) -> tuple[list[Incident], list[Incident]]:
        """The findings to store since the last call: (found or changed, retracted)."""
        found, retracted = list(self.found.values()), list(self.retracted.values())
        self.found.clear()
        self.retracted.clear()
        return found, retracted

    def give_back(self, found: Sequence[Incident], retracted: Sequence[Incident]) -> None:
        """Findings `take` gave that could not be stored: taken again next time, unless a
        later finding of the same incident replaced them."""
        for incident in found:
            if incident.incident_id not in self.retracted:
                self.found.setdefault(incident.incident_id, incident)
        for incident in retracted:
            if incident.incident_id not in self.found:
                self.retracted.setdefault(incident.incident_id, incident)

    def forget(self, now_ms: int) -> None:
        """Lets go of poses older than `keep_ms` (each robot's newest before stays, and a
        robot's poses since an ongoing incident of its own began) and of the incidents
        that ended before them and are not ongoing."""
        cut = now_ms - self.keep_ms
        if cut <= self.held_from_ms:
            return
        reach = self.th.lookback_ms
        since = dict.fromkeys(self.tracks, cut)
        for i in self.current.values():
            if i.ongoing:
                for r in i.robots:
                    since[r] = min(since.get(r, cut), i.start_ms - reach)
        # memory never grows back: what was let go of is read from the store
        since = {r: max(t, self._held(r)) for r, t in since.items()}
        self.held_from_ms = cut
        self.held_from = {r: t for r, t in since.items() if t < cut}
        for robot, track in self.tracks.items():
            at = bisect.bisect_left(track, since[robot], key=_ts)
            del track[: max(0, at - 1)]
        self.current_from_ms = cut - reach
        self.current = {
            k: i for k, i in self.current.items() if i.ongoing or i.end_ms >= cut - reach
        }

    # --- finding ------------------------------------------------------------------------

    def _note(self, incident: Incident) -> None:
        before = self.current.get(incident.incident_id)
        if before is not None and _key(before) == _key(incident):
            return
        self.current[incident.incident_id] = incident
        self.found[incident.incident_id] = incident
        self.retracted.pop(incident.incident_id, None)

    def _drop(self, incident: Incident) -> None:
        self.current.pop(incident.incident_id, None)
        self.found.pop(incident.incident_id, None)
        self.retracted[incident.incident_id] = incident

    def _poses(self, robot: str | None, from_ms: int) -> list[PoseRow]:
        """The stored poses of `robot` (of every robot if None) from `from_ms` on, with
        each robot's newest before it: from memory, and before the held span from the store."""
        robots = [robot] if robot is not None else list(self.tracks)
        lacking = [r for r in robots if from_ms < self._held(r)]
        out: list[PoseRow] = []
        if lacking:
            until = max(self._held(r) for r in lacking)
            read = self.read(
                from_ms, until, robot if robot is not None or len(lacking) > 1 else lacking[0]
            )
            wanted = set(lacking)
            out += [p for p in read if p.robot_id in wanted and p.ts_ms < self._held(p.robot_id)]
        for r in robots:
            track = self.tracks.get(r, [])
            if r in lacking:
                out += track[bisect.bisect_left(track, self._held(r), key=_ts) :]
            else:
                out += track[max(0, bisect.bisect_left(track, from_ms, key=_ts) - 1) :]
        return out

    def _held(self, robot: str) -> int:
        return self.held_from.get(robot, self.held_from_ms)

    def _redo(self, robots: set[str], from_ms: int, now_ms: int) -> None:
        off = self.th.offline_after_ms
        for robot in sorted(robots):
            self._redo_own(robot, from_ms - off, now_ms)
        self._redo_near_misses(robots, from_ms - off - self.th.tick_ms, now_ms)

    def _known(self, cut_ms: int) -> list[Incident]:
        """The latest finding of every incident ongoing or ending at or after `cut_ms`."""
        if cut_ms >= self.current_from_ms:
            return list(self.current.values())
        known = {i.incident_id: i for i in self.read_incidents(cut_ms, self.current_from_ms)}
        known.update(self.current)
        return list(known.values())

    def _redo_own(self, robot: str, cut_ms: int, now_ms: int) -> None:
        mine = [i for i in self._known(cut_ms) if i.kind in OWN_KINDS and i.robots == (robot,)]
        cut_ms = min([cut_ms, *(i.start_ms for i in mine if i.ongoing)])
        start = cut_ms - self.th.lookback_ms
        while True:
            track = unique_poses(self._poses(robot, start)).get(robot, [])
            fresh = [
                *stuck_incidents(track, self.th),
                *battery_low_incidents(track, self.th),
                *offline_incidents(track, now_ms, self.th),
            ]
            edge = [i for i in fresh if i.from_data_edge and i.end_ms >= cut_ms]
            if not edge or not self._earlier_exists(robot, track[0].ts_ms):
                break  # what reaches the data's edge starts there: the history has no more
            start -= 2 * (cut_ms - start)
        self._replace(
            [i for i in mine if i.end_ms >= cut_ms or i.ongoing],
            [i for i in fresh if i.end_ms >= cut_ms],
        )

    def _redo_near_misses(self, robots: set[str], cut_ms: int, now_ms: int) -> None:
        mine = [
            i
            for i in self._known(cut_ms)
            if i.kind == "near_miss" and robots.intersection(i.robots)
        ]
        cut_ms = min([cut_ms, *(i.start_ms for i in mine if i.ongoing)])
        start = cut_ms - self.th.offline_after_ms - self.th.tick_ms
        while True:
            tracks = unique_poses(self._poses(None, start))
            fresh = [
                i for i in near_miss_incidents(tracks, self.th) if robots.intersection(i.robots)
            ]
            edge = [i for i in fresh if i.from_data_edge and i.end_ms >= cut_ms]
            if not any(self._earlier_exists(r, tracks[r][0].ts_ms) for i in edge for r in i.robots):
                break  # what reaches the data's edge starts there: the history has no more
            start -= 2 * (cut_ms - start)
        self._replace(
            [i for i in mine if i.end_ms >= cut_ms or i.ongoing],
            [i for i in fresh if i.end_ms >= cut_ms],
        )

    def _earlier_exists(self, robot: str, ts_ms: int) -> bool:
        """Whether the store holds a pose of `robot` before `ts_ms`."""
        if ts_ms > self._held(robot):
            track = self.tracks.get(robot, [])
            return bool(track) and track[0].ts_ms < ts_ms
        return bool(self.read(ts_ms - self.th.lookback_ms, ts_ms, robot))

    def _replace(self, before: Iterable[Incident], fresh: Iterable[Incident]) -> None:
        fresh_ids = set()
        for incident in fresh:
            fresh_ids.add(incident.incident_id)
            self._note(incident)
        for incident in before:
            if incident.incident_id not in fresh_ids:
                self._drop(incident)
