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

An ongoing incident grows with every batch (a near miss's end, a stuck robot's seconds) or
with the clock (a silence, which `tick` finds): what is held here follows it exactly, but a
finding that only moved its end (incident_model.settled) is written again only when its end
crossed into another `refresh_ms` step. So a run that goes on costs a row every refresh, not
one per batch, and the stored row of an ongoing incident lags its end by less than a
refresh (readers extend an ongoing silence to now); any other change, and its end, is
written with the batch that found it.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterable, Sequence

import msgspec

from mapservice.core.incident_findings import UnstoredFindings
from mapservice.core.incident_joins import carried_on, joined_own
from mapservice.core.incident_model import can_still_grow, settled
from mapservice.core.incidents import (
    Incident,
    IncidentThresholds,
    battery_low_at,
    battery_low_incidents,
    offline_incidents,
    stuck_incidents,
    stuck_possible_at,
    unique_poses,
)
from mapservice.core.near_miss import Closest, near_misses, pose_columns, with_tracks
from mapservice.core.ports import PoseRow
from mapservice.core.recent_poses import RecentPoses

# A robot's own incidents; a near miss involves two.
OWN_KINDS = ("stuck", "battery_low", "offline")
# (from_ms, to_ms, robot_id or None for every robot) -> the stored poses in [from, to),
# and each robot's newest before from_ms
ReadPoses = Callable[[int, int, str | None], list[PoseRow]]
# (from_ms, to_ms) -> the stored incidents meeting [from, to)
ReadIncidents = Callable[[int, int], list[Incident]]


def _ts(pose: PoseRow) -> int:
    return pose.ts_ms


class IncidentTracker(UnstoredFindings):
    def __init__(
        self,
        read: ReadPoses,
        read_incidents: ReadIncidents,
        thresholds: IncidentThresholds | None = None,
        keep_ms: int = 300_000,
        refresh_ms: int = 10_000,
    ) -> None:
        if refresh_ms <= 0:
            raise ValueError("refresh_ms must be positive")
        self.read = read
        self.read_incidents = read_incidents
        self.th = thresholds or IncidentThresholds()
        self.keep_ms = keep_ms
        self.refresh_ms = refresh_ms
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
        # near misses found here (not read from the store): their closest tick, unrounded
        self.closest: dict[str, Closest] = {}
        # every robot's recent poses as columns, for the near misses of each batch
        self.recent = RecentPoses()
        self.found: dict[str, Incident] = {}  # new or changed findings, not taken yet
        self.retracted: dict[str, Incident] = {}

    # --- state --------------------------------------------------------------------------

    def load(
        self, poses: Iterable[PoseRow], held_from_ms: int, stored: Sequence[Incident], now_ms: int
    ) -> None:
        """Starts from the stored history: `poses` every stored pose from `held_from_ms` on
        (and each robot's newest before it), `stored` the incidents stored that meet that
        span or can still grow (incident_model.incidents_to_load). The rules then run over
        it, for what was stored but not yet found."""
        self.tracks = unique_poses(poses)
        self.recent.reset()
        self.held_from_ms = held_from_ms
        self.held_from = {}
        self.current = {i.incident_id: i for i in stored}
        self.current_from_ms = held_from_ms - self.th.lookback_ms
        self.closest = {}
        self.found.clear()
        self.retracted.clear()
        if self.tracks:
            self._redo(set(self.tracks), held_from_ms, now_ms)

    def add(self, poses: Sequence[PoseRow], now_ms: int) -> None:
        """A stored batch's poses (as the store keeps them, in the order stored)."""
        if not poses:
            return
        th = self.th
        # Poses older than memory (late ones, a backlog read again): one read of the store
        # brings memory back to where the rules will look, instead of a read per pose.
        oldest = min(p.ts_ms for p in poses)
        self._cover(oldest - 2 * th.lookback_ms - th.tick_ms)
        self.recent.add(poses)
        newest_before: dict[str, PoseRow | None] = {}
        first_new_of: dict[str, int] = {}
        # Robots whose own incidents the new poses may change (the others' new poses all
        # came after their newest and start no condition nor silence: their own rules find
        # nothing new unless one of their incidents is ongoing, checked below).
        eventful: set[str] = set()
        # The earliest instant the batch can change: each new pose's place at the ticks
        # from the pose before it (found here for a pose after its robot's newest, below
        # for the others).
        changed_from = oldest
        placed_later: list[PoseRow] = []
        held_from, held_from_ms = self.held_from, self.held_from_ms
        tracks, off = self.tracks, th.offline_after_ms
        for pose in poses:
            robot, ts = pose.robot_id, pose.ts_ms
            track = tracks.get(robot)
            if track is None:
                track = tracks[robot] = []
            last = track[-1] if track else None
            if robot not in newest_before:
                newest_before[robot] = last
                first_new_of[robot] = ts
            if last is not None and ts > last.ts_ms and ts > held_from.get(robot, held_from_ms):
                track.append(pose)
                if last.ts_ms < changed_from:
                    changed_from = last.ts_ms
                if (
                    ts - last.ts_ms > off
                    or battery_low_at(pose, th)
                    or stuck_possible_at(last, pose, th)
                ):
                    eventful.add(robot)
                continue
            first_new_of[robot] = min(first_new_of[robot], ts)
            eventful.add(robot)
            placed_later.append(pose)
            at = bisect.bisect_left(track, ts, key=_ts)
            if at < len(track) and track[at].ts_ms == ts:
                track[at] = pose  # the store keeps the last written
            else:
                track.insert(at, pose)
        for p in placed_later:
            changed_from = min(changed_from, self._pose_before(p.robot_id, p.ts_ms, p.ts_ms))
        known = self._known(changed_from - th.lookback_ms)
        ongoing_own: dict[str, dict[str, Incident]] = {}
        for i in known:
            if i.ongoing and i.kind in OWN_KINDS:
                ongoing_own.setdefault(i.robots[0], {})[i.kind] = i
        for robot, before in newest_before.items():
            ongoing = ongoing_own.get(robot, {})
            if (
                robot not in eventful
                and not ongoing
                and now_ms - self.tracks[robot][-1].ts_ms <= th.offline_after_ms
            ):
                continue  # the rules over its new poses would find nothing
            first_new = first_new_of[robot]
            if before is None or first_new > before.ts_ms:
                if self._append_own(robot, before, first_new, ongoing, now_ms):
                    continue
            self._redo_own(robot, first_new - th.offline_after_ms, now_ms, known)
        late = {p.robot_id for p in placed_later}
        self._redo_near_misses(set(newest_before), changed_from, known, now_ms, late)

    def _pose_before(self, robot: str, ts_ms: int, default: int) -> int:
        """The time of the stored pose of `robot` before `ts_ms` (`default` if none)."""
        if ts_ms <= self._held(robot):
            earlier = [p.ts_ms for p in self.read(ts_ms, ts_ms, robot) if p.ts_ms < ts_ms]
            return max(earlier, default=default)
        track = self.tracks.get(robot, [])
        at = bisect.bisect_left(track, ts_ms, key=_ts)
        return track[at - 1].ts_ms if at > 0 else default

    def tick(self, now_ms: int) -> None:
        """Silences that began or turned critical as the clock moved."""
        for track in self.tracks.values():
            if not track or now_ms - track[-1].ts_ms <= self.th.offline_after_ms:
                continue
            for incident in offline_incidents(track[-1:], now_ms, self.th):
                self._note(incident)

    def forget(self, now_ms: int) -> None:
        """Lets go of poses older than `keep_ms` (each robot's newest before stays, and a
        robot's poses since an incident of it that can still grow began) and of the
        incidents that ended before them and cannot grow."""
        cut = now_ms - self.keep_ms
        # In steps of a twentieth of what is kept, not every batch: each step walks every
        # robot's track, and what is held a little longer is only read from memory again.
        if cut - self.held_from_ms < max(1, self.keep_ms // 20):
            return
        reach = self.th.lookback_ms
        since = dict.fromkeys(self.tracks, cut)
        growing = {k for k, i in self.current.items() if can_still_grow(i, now_ms, self.th)}
        for k in growing:
            i = self.current[k]
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
            k: i for k, i in self.current.items() if k in growing or i.end_ms >= cut - reach
        }
        self.closest = {k: c for k, c in self.closest.items() if k in self.current}

    # --- finding ------------------------------------------------------------------------

    def _note(self, incident: Incident) -> None:
        key = incident.incident_id
        before = self.current.get(key)
        self.current[key] = incident
        if (
            before is not None
            and key not in self.found  # else the newest finding replaces the one waiting
            and before.end_ms // self.refresh_ms == incident.end_ms // self.refresh_ms
            and settled(before) == settled(incident)
        ):
            return
        self.found[key] = incident
        self.retracted.pop(key, None)

    def _tracks(self, robot: str | None, from_ms: int) -> dict[str, list[PoseRow]]:
        """The stored poses of `robot` (of every robot if None) from `from_ms` on, with
        each robot's newest before it, per robot in time order: from memory, and before the
        held span from the store."""
        if robot is not None and from_ms >= self._held(robot):  # in memory
            track = self.tracks.get(robot)
            if not track:
                return {}
            return {robot: track[max(0, bisect.bisect_left(track, from_ms, key=_ts) - 1) :]}
        robots = [robot] if robot is not None else list(self.tracks)
        lacking = [r for r in robots if from_ms < self._held(r)]
        out: dict[str, list[PoseRow]] = {}
        for r in robots:
            if r not in lacking:
                track = self.tracks.get(r, [])
                out[r] = track[max(0, bisect.bisect_left(track, from_ms, key=_ts) - 1) :]
        if lacking:
            until = max(self._held(r) for r in lacking)
            read = self.read(
                from_ms, until, robot if robot is not None or len(lacking) > 1 else lacking[0]
            )
            wanted = set(lacking)
            rows = [p for p in read if p.robot_id in wanted and p.ts_ms < self._held(p.robot_id)]
            for r in lacking:
                track = self.tracks.get(r, [])
                rows += track[bisect.bisect_left(track, self._held(r), key=_ts) :]
            out.update(unique_poses(rows))
        return {r: t for r, t in out.items() if t}

    def track(self, robot: str, from_ms: int) -> list[PoseRow]:
        """The stored poses of `robot` from `from_ms` on, and its newest before, in order."""
        return self._tracks(robot, from_ms).get(robot, [])

    def _held(self, robot: str) -> int:
        return self.held_from.get(robot, self.held_from_ms)

    def _redo(self, robots: set[str], from_ms: int, now_ms: int) -> None:
        """Everything the poses of `robots` from `from_ms` on can change, the slow way."""
        # Each robot's own rules look back from a silence before from_ms: one read of every
        # robot's poses there, not one read of the store per robot (a rebuild of a thousand
        # robots would take minutes, longer than the consumer's poll interval).
        self._cover(from_ms - self.th.offline_after_ms - self.th.lookback_ms)
        known = self._known(from_ms - self.th.lookback_ms)
        for robot in sorted(robots):
            self._redo_own(robot, from_ms - self.th.offline_after_ms, now_ms, known)
        self._redo_near_misses(robots, from_ms, known, now_ms)

    def _cover(self, from_ms: int) -> None:
        """Memory holds every stored pose from `from_ms` on (and each robot's newest before
        it): what it lacks read from the store at once."""
        if from_ms >= self.held_from_ms:
            return
        read = unique_poses(self.read(from_ms, self.held_from_ms, None))
        for robot, rows in read.items():
            held = self._held(robot)
            older = [p for p in rows if p.ts_ms < held]
            # the store's and memory's poses; memory's last (it holds what was stored last)
            self.tracks[robot] = unique_poses(older + self.tracks.get(robot, [])).get(robot, [])
        self.held_from_ms = from_ms
        self.held_from = {r: t for r, t in self.held_from.items() if t < from_ms}

    def _append_own(
        self,
        robot: str,
        before: PoseRow | None,
        first_new_ms: int,
        ongoing: dict[str, Incident],
        now_ms: int,
    ) -> bool:
        """A robot's own incidents when its new poses all come after its newest (the live
        case): the rules run over the new poses and the windows they look back on only,
        and a run that goes on from the one ongoing is joined to it (the poses before the
        new ones are unchanged, and so is their part of the run). False when what is known
        does not fit (then the slow way)."""
        th = self.th
        seg_from = (before.ts_ms if before else first_new_ms) - th.stuck_ms - th.offline_after_ms
        track = self._tracks(robot, seg_from).get(robot, [])
        recent = track[
            bisect.bisect_left(track, before.ts_ms if before else first_new_ms, key=_ts) :
        ]
        fresh = [
            # judged from the newest pose before the new ones: a run through it is the one
            # ongoing, joined below
            *stuck_incidents(track, th, before.ts_ms if before else first_new_ms),
            # the others look at no pose before it
            *battery_low_incidents(recent, th),
            *offline_incidents(recent, now_ms, th),
        ]
        continued: set[str] = set()
        noted: list[Incident] = []
        for incident in fresh:
            if incident.end_ms < first_new_ms:
                continue  # before the new poses: unchanged
            if (
                before is not None
                and incident.kind in ("stuck", "battery_low")
                and incident.evidence[0].ts_ms <= before.ts_ms
            ):
                went_on = ongoing.get(incident.kind)
                if went_on is None:
                    return False
                incident = joined_own(went_on, incident, th)
                continued.add(incident.kind)
            noted.append(incident)
        for incident in noted:
            self._note(incident)
        fresh_ids = {i.incident_id for i in noted}
        for kind, incident in ongoing.items():
            if kind == "offline":
                if incident.incident_id not in fresh_ids:
                    self._drop(incident)  # its silence was shorter than it seemed
            elif kind not in continued:
                self._note(msgspec.structs.replace(incident, ongoing=False))
        return True

    def _known(self, cut_ms: int) -> list[Incident]:
        """The latest finding of every incident ongoing or ending at or after `cut_ms`."""
        if cut_ms >= self.current_from_ms:
            return list(self.current.values())
        return self._held_over(self.read_incidents(cut_ms, self.current_from_ms))

    def _redo_own(
        self, robot: str, cut_ms: int, now_ms: int, known: Iterable[Incident] | None = None
    ) -> None:
        known = self._known(cut_ms) if known is None else known
        mine = [i for i in known if i.kind in OWN_KINDS and i.robots == (robot,)]
        cut_ms = min([cut_ms, *(i.start_ms for i in mine if i.ongoing)])
        start = cut_ms - self.th.lookback_ms
        while True:
            track = self._tracks(robot, start).get(robot, [])
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
            [i for i in mine if i.end_ms >= cut_ms or can_still_grow(i, now_ms, self.th)],
            [i for i in fresh if i.end_ms >= cut_ms],
        )

    def _redo_near_misses(
        self,
        robots: set[str],
        changed_from_ms: int,
        known: Iterable[Incident],
        now_ms: int,
        late: set[str] | None = None,
    ) -> None:
        """The near misses of pairs with a robot of `robots` at the ticks from
        `changed_from_ms` on, each run from its start: the ticks before are unchanged, so
        a known run that reaches them keeps its start (`known`: every incident ongoing or
        ending at or after changed_from_ms - lookback). A run that can still grow reaches
        them whatever its end: read from the store after a restart, its end lags.
        `late`: the robots with poses placed before their newest (None: any may have)."""
        tick = self.th.tick_ms
        first_tick = -(-changed_from_ms // tick) * tick
        reaching = [
            i
            for i in known
            if i.kind == "near_miss"
            and robots.intersection(i.robots)
            and (i.end_ms >= first_tick - tick or can_still_grow(i, now_ms, self.th))
        ]
        # A run begun before the changed ticks whose robots' new poses all came after their
        # newest has no tick that can change: carried on from its closest tick found here
        # (`carried_on`), not judged again from its start (a pair side by side for an hour
        # would cost an hour of ticks a batch).
        joinable = {
            i.robots: i
            for i in reaching
            if i.start_ms < first_tick
            and late is not None
            and not late.intersection(i.robots)
            and i.incident_id in self.closest
        }
        # Every pair from the changed ticks on, but the other pairs whose known run reaches
        # them: those from their run's start (their robots only).
        going_on: dict[tuple[str, ...], int] = {}
        for i in reaching:  # from the first of a pair's runs that reach them, or from them
            if i.robots not in joinable:
                going_on[i.robots] = min(i.start_ms, first_tick, going_on.get(i.robots, first_tick))
        if first_tick >= self.held_from_ms:  # memory holds them: the columns kept
            cols = self.recent.columns(first_tick, self.tracks)
        else:
            cols = pose_columns(self._tracks(None, first_tick))
        # the going-on pairs' robots from the earliest of their pairs' starts
        reach_from: dict[str, int] = {}
        for pair, start in going_on.items():
            for r in pair:
                reach_from[r] = min(start, reach_from.get(r, start))
        reach = {r: t for r, at in reach_from.items() for r, t in self._tracks(r, at).items()}
        closest: dict[str, Closest] = {}
        fresh, closest = carried_on(
            joinable,
            self.closest,
            near_misses(
                with_tracks(cols, reach),
                self.th,
                from_tick=first_tick,
                involving=robots,
                pairs_from={(a, b): start for (a, b), start in going_on.items()},
                closest=closest,
            ),
            closest,
            first_tick,
            tick,
            lambda robot: self.tracks[robot][-1].ts_ms,
        )
        self.closest.update(closest)
        # A run that ends before the changed ticks is unchanged: the one known stands (one
        # known as going on is found again, its end with it).
        judged = {i.incident_id for i in reaching}
        self._replace(
            reaching,
            [i for i in fresh if i.end_ms >= first_tick - tick or i.incident_id in judged],
        )

    def _earlier_exists(self, robot: str, ts_ms: int) -> bool:
        """Whether the store holds a pose of `robot` before `ts_ms`."""
        if ts_ms > self._held(robot):
            track = self.tracks.get(robot, [])
            return bool(track) and track[0].ts_ms < ts_ms
        return bool(self.read(ts_ms - self.th.lookback_ms, ts_ms, robot))
