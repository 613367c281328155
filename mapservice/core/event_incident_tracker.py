"""Live detection of the incidents found from stored records (event_incidents.py: zone
violations, conflicts, VDA 5050 errors and connection states, failed commands), beside the
pose incidents' tracker (incident_tracker.py), whose poses place them. As there, each
robot's recent records are held in memory and, when a batch brings some, its rules run
again over the part of its history the batch can change; what they find there replaces
what was found before. So the incidents found live, whatever order the records came in,
are the ones a recomputation of the stored history finds.

What a robot's new records from instant `m` on can change, per family of records: its
incidents of their kind that are ongoing or end at or after m - margin (the zone runs: a
silence, `offline_after_ms`; conflicts: `conflict_gap_ms`; the state runs: nothing), each
run from its start. A command's failure depends on that command's issue and acks alone; a
silence of acks is judged by the clock (`tick`). An incident placed by a robot's pose is
placed again when a pose of it at or before its evidence's instant comes.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import msgspec

from mapservice.core.commands import CommandIssued, StoredCommandEvent
from mapservice.core.event_incidents import (
    EVENT_KINDS,
    EventRecords,
    Locate,
    VdaErrorsAt,
    command_failed,
    conflict_incidents,
    connection_offline_incidents,
    grows_with_the_clock,
    is_connection_offline,
    later_state,
    merged_errors,
    placed,
    vda_error_incidents,
    zone_violation_incidents,
)
from mapservice.core.incident_findings import UnstoredFindings
from mapservice.core.incident_model import (
    OFFLINE_CRITICAL_S,
    Incident,
    IncidentThresholds,
    PoseRef,
    can_still_grow,
    incident_id,
)
from mapservice.core.ports import PoseRow

# (from_ms, to_ms, robot_id or None for every robot) -> the records stored in [from, to)
ReadRecords = Callable[[int, int, str | None], EventRecords]
# (from_ms, to_ms) -> the stored incidents meeting [from, to)
ReadIncidents = Callable[[int, int], list[Incident]]
# (robot, from_ms) -> its stored poses from then on, and its newest before
ReadTrack = Callable[[str, int], list[PoseRow]]
FAMILIES = ("zone", "conflict", "vda", "connection")


def is_event_incident(incident: Incident) -> bool:
    """Whether the rules here find it (else incidents.py's)."""
    return incident.kind in EVENT_KINDS or is_connection_offline(incident)


def _family(incident: Incident) -> str:
    """Which records an incident is found from (FAMILIES, or a command's)."""
    return {
        "zone_violation": "zone",
        "conflict": "conflict",
        "vda_error": "vda",
        "offline": "connection",
    }.get(incident.kind, "command")


def _key(incident: Incident) -> Incident:
    """What a new finding must differ in to be written again: an ongoing disconnection's
    or error's end and length grow with the clock."""
    if grows_with_the_clock(incident):
        return msgspec.structs.replace(incident, end_ms=0, measure=0.0)
    return incident


class EventIncidentTracker(UnstoredFindings):
    def __init__(
        self,
        read: ReadRecords,
        read_incidents: ReadIncidents,
        track: ReadTrack,
        thresholds: IncidentThresholds | None = None,
        keep_ms: int = 300_000,
    ) -> None:
        self.read, self.read_incidents, self.track = read, read_incidents, track
        self.th = thresholds or IncidentThresholds()
        self.keep_ms = keep_ms
        # family -> robot -> key -> record: zone (instant -> zone), conflict ((instant,
        # row, column) -> row), vda and connection (instant -> state)
        self.records: dict[str, dict[str, dict[Any, Any]]] = {
            f: defaultdict(dict) for f in FAMILIES
        }
        self.issued: dict[str, StoredCommandEvent] = {}  # by command id
        self.acks: dict[str, list[StoredCommandEvent]] = defaultdict(list)
        self.pending: set[str] = set()  # commands issued whose ack deadline has not passed
        # each vehicle's newest VDA state given since the load (all of them, as stored)
        self.newest_state: dict[str, int] = {}
        # Memory holds each robot's records from its instant here (the default for robots
        # not named) on; earlier ones are read from the store.
        self.held_from_ms = 0
        self.held_from: dict[str, int] = {}
        # By id, the latest finding of each incident ongoing or ended at or after
        # `current_from_ms`; the earlier ones are read from the store.
        self.current: dict[str, Incident] = {}
        self.current_from_ms = 0
        self.found: dict[str, Incident] = {}
        self.retracted: dict[str, Incident] = {}

    # --- state --------------------------------------------------------------------------

    def load(
        self,
        records: EventRecords,
        held_from_ms: int,
        stored: Sequence[Incident],
        now_ms: int,
        robots: Iterable[str] = (),
    ) -> None:
        """Starts from the stored records from `held_from_ms` on and the incidents stored
        that meet that span or can still grow (incident_model.incidents_to_load); the
        rules then run over them, for what was not yet found.
        Call after the pose tracker loaded (its poses place the incidents), with the robots
        it holds (`robots`): one may stand in a zone since before the span."""
        self.records = {f: defaultdict(dict) for f in FAMILIES}
        self.issued.clear()
        self.acks.clear()
        self.pending.clear()
        self.newest_state.clear()
        self.held_from_ms, self.held_from = held_from_ms, {}
        self.current = {i.incident_id: i for i in stored if is_event_incident(i)}
        self.current_from_ms = held_from_ms - self.th.lookback_ms
        self.found.clear()
        self.retracted.clear()
        self._remember(records)
        touched = {(f, r): held_from_ms for f, held in self.records.items() for r in held}
        touched.update({("zone", r): held_from_ms for r in robots})
        for i in self.current.values():
            if _family(i) in FAMILIES:
                touched[(_family(i), i.robots[0])] = held_from_ms
        self._redo(touched, set(self.issued), now_ms)

    def add(self, poses: Sequence[PoseRow], records: EventRecords, now_ms: int) -> None:
        """A stored batch: its poses (already given to the pose tracker) and records."""
        touched: dict[tuple[str, str], int] = {}

        def touch(family: str, robot: str, ts_ms: int) -> None:
            touched[(family, robot)] = min(ts_ms, touched.get((family, robot), ts_ms))

        for v in records.violations:
            touch("zone", v.robot_id, v.ts_ms)
        for c in records.conflicts:
            touch("conflict", c.robot_b, c.ts_ms)
        for s in records.vda_states:
            touch("vda", s.robot_id, s.ts_ms)
        for n in records.connections:
            touch("connection", n.robot_id, n.ts_ms)
        self._cover(min(touched.values(), default=now_ms) - self.th.lookback_ms)
        commands = self._commands_of(records.commands)
        self._remember(records)
        self._read_clears_again(records.vda_states, now_ms)
        first_pose: dict[str, int] = {}
        for p in poses:
            first_pose[p.robot_id] = min(p.ts_ms, first_pose.get(p.robot_id, p.ts_ms))
        if first_pose:
            # the zone runs the new poses can end, extend or split (by a pose outside)
            zoned = {i.robots[0] for i in self.current.values() if i.kind == "zone_violation"}
            for robot, ts in first_pose.items():
                if robot in zoned or ts - self.th.offline_after_ms < self.current_from_ms:
                    touch("zone", robot, ts)
        self._redo(touched, commands, now_ms)
        if first_pose:
            self._place_again(first_pose)

    def tick(self, now_ms: int) -> None:
        """Commands whose ack deadline passed, and disconnections as the clock moves."""
        due = [
            k
            for k in self.pending
            if self.issued[k].ts_ms + self.th.command_ack_timeout_ms < now_ms
        ]
        if due:
            self._redo({}, set(due), now_ms)
        for incident in list(self.current.values()):
            if not grows_with_the_clock(incident):
                continue
            off_s = (now_ms - incident.start_ms) / 1000
            severity = incident.severity
            if incident.kind == "offline":
                severity = "critical" if off_s >= OFFLINE_CRITICAL_S else "warning"
            if severity != incident.severity or now_ms - incident.end_ms > self.keep_ms // 2:
                # rewritten as it turns critical, and now and then so that a read of a
                # recent span (the list's) still meets it by its stored end
                grown = msgspec.structs.replace(
                    incident, end_ms=now_ms, measure=off_s, severity=severity
                )
                self._note(grown, force=True)

    def forget(self, now_ms: int) -> None:
        """Lets go of records older than `keep_ms` (a robot's since an incident of it that
        can still grow began stay: each batch that extends it judges it from its start)
        and of the incidents that ended before them and cannot grow."""
        cut = now_ms - self.keep_ms
        if cut - self.held_from_ms < max(1, self.keep_ms // 20):
            return
        reach = self.th.lookback_ms
        since: dict[str, int] = {}
        growing = {k for k, i in self.current.items() if can_still_grow(i, now_ms, self.th)}
        for k in growing:
            i = self.current[k]
            since[i.robots[0]] = min(since.get(i.robots[0], cut), i.start_ms - reach)
        # memory never grows back: what was let go of is read from the store
        since = {r: max(t, self._held(r)) for r, t in since.items()}
        for robots in self.records.values():
            for robot, rows in robots.items():
                keep_from = since.get(robot, cut)
                for key in [k for k in rows if _instant(k) < keep_from]:
                    del rows[key]
        self.held_from_ms = cut
        self.held_from = {r: t for r, t in since.items() if t < cut}
        for k, c in list(self.issued.items()):
            if k not in self.pending and c.ts_ms < since.get(c.event.robot_id, cut):
                del self.issued[k]
        for k, acks in list(self.acks.items()):
            kept = [a for a in acks if a.ts_ms >= since.get(a.event.robot_id, cut)]
            if kept:
                self.acks[k] = kept
            else:
                del self.acks[k]
        self.current_from_ms = cut - reach
        self.current = {
            k: i for k, i in self.current.items() if k in growing or i.end_ms >= cut - reach
        }

    # --- finding ------------------------------------------------------------------------

    def _remember(self, records: EventRecords) -> None:
        rec = self.records
        for v in records.violations:
            at = rec["zone"][v.robot_id]
            at[v.ts_ms] = min(at.get(v.ts_ms, v.annotation_id), v.annotation_id)
        for c in records.conflicts:
            rows = rec["conflict"][c.robot_b]
            key = (c.ts_ms, c.row, c.column)
            if key not in rows or c.ts_a_ms >= rows[key].ts_a_ms:
                rows[key] = c
        for e in records.vda_states:
            states = rec["vda"][e.robot_id]
            states[e.ts_ms] = merged_errors(states[e.ts_ms], e) if e.ts_ms in states else e
        for n in records.connections:
            conns = rec["connection"][n.robot_id]
            conns[n.ts_ms] = later_state(conns[n.ts_ms], n) if n.ts_ms in conns else n
        for m in records.commands:
            command = m.event.command_id
            if isinstance(m.event, CommandIssued):
                known = self.issued.get(command)
                if known is None or (m.ts_ms, m.event_id) < (known.ts_ms, known.event_id):
                    self.issued[command] = m
                    self.pending.add(command)
            else:  # of two with one id, the last given, as the store keeps the last written
                acks = self.acks[command]
                acks[:] = [a for a in acks if a.event_id != m.event_id] + [m]

    def _read_clears_again(self, states: Sequence[VdaErrorsAt], now_ms: int) -> None:
        """A state with a FATAL error that comes before a stored state of its vehicle: the
        next state, if it has no errors, ends it. Of the states without errors the store
        gives only those after one with errors (the others change nothing) as they were
        when read, so memory read from the store may lack the one a late state now ends
        its errors with: read again from the store (the late ones stored). Memory knows
        which states are the newest from those it was given since it was loaded: the
        first state with errors of each vehicle after that is read again once, the late
        ones later on."""
        earliest: dict[str, int] = {}
        for state in states:
            if state.fatal:
                earliest[state.robot_id] = min(
                    state.ts_ms, earliest.get(state.robot_id, state.ts_ms)
                )
        for robot, ts in earliest.items():
            newest = self.newest_state.get(robot)
            if newest is None or ts < newest:
                until = max(now_ms, newest or now_ms) + 1
                start = max(ts, self._held(robot))
                self._remember(EventRecords(vda_states=self.read(start, until, robot).vda_states))
        for state in states:
            newest = self.newest_state.get(state.robot_id, state.ts_ms)
            self.newest_state[state.robot_id] = max(newest, state.ts_ms)

    def _commands_of(self, commands: Iterable[StoredCommandEvent]) -> set[str]:
        """The commands `commands` name, their issues and acks brought into memory first
        (an ack counts within the timeout of its command's issue, before or after)."""
        ids: set[str] = set()
        robots: dict[str, int] = {}
        for c in commands:
            ids.add(c.event.command_id)
            earliest = c.ts_ms - self.th.command_ack_timeout_ms
            robots[c.event.robot_id] = min(earliest, robots.get(c.event.robot_id, earliest))
        for robot, earliest in robots.items():
            self._hold(robot, earliest)
        return ids

    def _redo(self, touched: dict[tuple[str, str], int], commands: set[str], now_ms: int) -> None:
        margin = {
            "zone": self.th.offline_after_ms,
            "conflict": self.th.conflict_gap_ms,
            "vda": 0,
            "connection": 0,
        }
        # An ongoing run is judged again from its start (the new records may end it), and
        # so is every run ending after that: all of them known, read from the store if
        # memory lacks them (ongoing ones it always holds).
        ongoing: dict[tuple[str, str], int] = {}
        for i in self.current.values():
            key = (_family(i), i.robots[0])
            if i.ongoing and key in touched:
                ongoing[key] = min(i.start_ms, ongoing.get(key, i.start_ms))
        cut_of = {key: min(m - margin[key[0]], ongoing.get(key, m)) for key, m in touched.items()}
        cuts = [*cut_of.values()]
        cuts += [self.issued[k].ts_ms for k in commands if k in self.issued]
        if not cuts:
            return
        known = self._known(min(cuts))
        mine: dict[tuple[str, str], list[Incident]] = defaultdict(list)
        for i in known:
            mine[(_family(i), i.robots[0])].append(i)
        for (family, robot), cut in sorted(cut_of.items()):
            before = [i for i in mine.get((family, robot), []) if i.ongoing or i.end_ms >= cut]
            if family == "zone":
                went_on = self._zone_going_on(robot, before, touched[(family, robot)])
                if went_on is not None:
                    self._replace(before, went_on)
                    continue
            start = min([cut, *(i.start_ms for i in before)])
            fresh = self._rule(family, robot, start, cut, now_ms, before)
            self._replace(before, [i for i in fresh if i.ongoing or i.end_ms >= cut])
        by_id = {i.incident_id: i for i in known}
        for k in sorted(commands):
            issued = self.issued.get(k)
            if issued is None:
                continue  # an ack whose command is not stored
            if issued.ts_ms + self.th.command_ack_timeout_ms < now_ms:
                self.pending.discard(k)
            robot = issued.event.robot_id
            self._hold(robot, issued.ts_ms - self.th.command_ack_timeout_ms)  # its acks
            failed = command_failed(issued, self.acks.get(k, []), now_ms, self.th)
            was = by_id.get(incident_id("command_failed", (robot, k), issued.ts_ms))
            self._replace([was] if was else [], [placed(failed, self._locate)] if failed else [])

    def _rule(
        self,
        family: str,
        robot: str,
        start: int,
        cut: int,
        now_ms: int,
        before: Sequence[Incident] = (),
    ) -> list[Incident]:
        """The family's incidents of `robot` from `start` on, placed. An evidence the known
        incidents (`before`) hold keeps its place: a run that goes on (conflicts a few
        seconds apart for an hour) is judged again from its start with every batch, and
        its first evidence lies before memory's poses, so locating it again would read
        the store each batch. A late pose that moves it is placed by `_place_again`."""
        if family == "zone":
            return self._zone_runs(robot, start, cut)
        rows = self._rows(family, robot, start)
        found: list[Incident]
        if family == "conflict":
            found = conflict_incidents(list(rows.values()), self.th)
        elif family == "vda":
            found = vda_error_incidents([rows[t] for t in sorted(rows)], now_ms)
        else:
            found = connection_offline_incidents([rows[t] for t in sorted(rows)], now_ms)
        locate = self._locator([e for i in before for e in i.evidence])
        return [placed(i, locate) for i in found]

    def _zone_going_on(
        self, robot: str, before: list[Incident], first_new_ms: int
    ) -> list[Incident] | None:
        """The robot's zone runs when its one ongoing run's poses are all older than the new
        records (the live case): judged from that run's last pose on only, the run carried
        on from it (a robot may stand in a zone for longer than memory holds, and its
        poses since the run began are not read again each batch). None when that does not
        fit (then the slow way)."""
        if len(before) != 1 or not before[0].ongoing or first_new_ms <= before[0].end_ms:
            return None
        going = before[0]
        track = self.track(robot, going.end_ms)
        zones = self._rows("zone", robot, track[0].ts_ms if track else going.end_ms)
        fresh = zone_violation_incidents(track, zones, self.th)
        runs = [i for i in fresh if i.start_ms <= going.end_ms <= i.end_ms]
        if len(runs) != 1:
            return None
        run = runs[0]
        carried = msgspec.structs.replace(
            run,
            incident_id=going.incident_id,
            start_ms=going.start_ms,
            x=going.x,
            y=going.y,
            measure=(run.end_ms - going.start_ms) / 1000,
            evidence=(going.evidence[0], run.evidence[1]),
            from_data_edge=False,
        )
        return [carried, *(i for i in fresh if i.start_ms > going.end_ms)]

    def _zone_runs(self, robot: str, start: int, cut: int) -> list[Incident]:
        """The robot's zone runs from `start` on, each whole: one kept (ongoing, or ending
        at or after `cut`) that reaches back to the first pose read is read again from
        further back (a robot may stand in a zone for longer than memory holds)."""
        reach = self.th.offline_after_ms
        while True:
            track = self.track(robot, start - reach)
            zones = self._rows("zone", robot, track[0].ts_ms if track else start)
            fresh = zone_violation_incidents(track, zones, self.th)
            if not track or track[0].ts_ms >= start - reach:
                return fresh  # the robot's first pose: nothing before
            if not any(i.from_data_edge and (i.ongoing or i.end_ms >= cut) for i in fresh):
                return fresh
            reach *= 2

    def _rows(self, family: str, robot: str, start: int) -> dict[Any, Any]:
        """The robot's records of the family from `start` on (read from the store into
        memory if it does not hold them)."""
        self._hold(robot, start)
        rows = self.records[family].get(robot, {})
        return {k: v for k, v in rows.items() if _instant(k) >= start}

    def _hold(self, robot: str, start: int) -> None:
        """Memory holds the robot's records from `start` on (read from the store if not)."""
        if start < self._held(robot):
            self._remember(self.read(start, self._held(robot), robot))
            self.held_from[robot] = start

    def _locator(self, kept: Iterable[PoseRef]) -> Locate:
        """Places evidence where `kept` placed it already, and the rest from the poses."""
        places = {(e.robot_id, e.ts_ms): (e.x, e.y) for e in kept}

        def locate(robot: str, ts_ms: int) -> tuple[float, float] | None:
            place = places.get((robot, ts_ms))
            return place if place is not None else self._locate(robot, ts_ms)

        return locate

    def _locate(self, robot: str, ts_ms: int) -> tuple[float, float] | None:
        track = self.track(robot, ts_ms + 1)
        return (track[0].x, track[0].y) if track and track[0].ts_ms <= ts_ms else None

    def _place_again(self, first_pose: dict[str, int]) -> None:
        """Incidents whose evidence a new pose (at or before its instant) places anew."""
        earliest = min(first_pose.values())
        for incident in self._known(earliest):
            if incident.kind == "zone_violation" or not any(
                e.ts_ms >= first_pose.get(e.robot_id, e.ts_ms + 1) for e in incident.evidence
            ):
                continue
            # only the evidence at or after its robot's first new pose can move
            kept = [
                e for e in incident.evidence if e.ts_ms < first_pose.get(e.robot_id, e.ts_ms + 1)
            ]
            self._note(placed(incident, self._locator(kept)))

    def _cover(self, from_ms: int) -> None:
        """Memory holds every robot's records from `from_ms` on: read from the store at
        once for a batch of late records, not per robot."""
        if from_ms >= self.held_from_ms:
            return
        self._remember(self.read(from_ms, self.held_from_ms, None))
        self.held_from_ms = from_ms
        self.held_from = {r: t for r, t in self.held_from.items() if t < from_ms}

    def _held(self, robot: str) -> int:
        return self.held_from.get(robot, self.held_from_ms)

    def _known(self, cut_ms: int) -> list[Incident]:
        if cut_ms >= self.current_from_ms:
            return list(self.current.values())
        stored = self.read_incidents(cut_ms, self.current_from_ms)
        return self._held_over(i for i in stored if is_event_incident(i))

    def _note(self, incident: Incident, force: bool = False) -> None:
        before = self.current.get(incident.incident_id)
        if not force and before is not None and _key(before) == _key(incident):
            return
        self.current[incident.incident_id] = incident
        self.found[incident.incident_id] = incident
        self.retracted.pop(incident.incident_id, None)


def _instant(key: int | tuple[int, int, int]) -> int:
    return key if isinstance(key, int) else key[0]
