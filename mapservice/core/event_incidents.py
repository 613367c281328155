"""Incidents found from what the processors store beside the poses: the zone violations
(processors/zone_watch.py finds them), the map conflicts (conflict_recorder.py), VDA 5050
vehicles' states and connection states, and operators' commands with the robots' acks. Pure
rules over those stored records, like incidents.py's over the poses, so that the live
detection (event_incident_tracker.py) and a recomputation of any past span give the same
incidents.

- **zone_violation**: a maximal run of a robot's consecutive poses that lie in one keep-out
  zone (a stored violation at each), with no silence longer than `offline_after_ms` inside;
  ongoing while its last pose is the robot's newest. Critical: a keep-out zone is a safety
  matter. The figure is the seconds inside.
- **conflict**: one robot's conflicting chunk writes (it wrote what another robot had
  written differently within the conflict window), those no further apart than
  `conflict_gap_ms` making one incident; its robots are that robot, then the others whose
  writes it contradicted. Never ongoing (a later conflict within the gap extends it). The
  figure is how many conflicting chunk writes.
- **vda_error**: a FATAL error a VDA 5050 vehicle reports in its `state`, of one type: from
  the first state that lists it to the first later state that does not (a state's errors
  hold until its next state); while no such state came it is ongoing, up to `until_ms`.
  Critical.
- **command_failed**: a command the robot refused (its first ack `rejected`: from the issue
  to the ack), or did not acknowledge within `command_ack_timeout_ms` of the issue (judged
  once the history is known past the deadline: from the issue to the deadline). An ack
  counts within the timeout of the issue, before it too (a robot's clock may run behind).
  Warning.
- **offline** (connection): a VDA 5050 vehicle's `connection` state OFFLINE or
  CONNECTIONBROKEN: from it to the next ONLINE, ongoing (up to `until_ms`) until then. Of
  several states at one instant the last by name counts (ONLINE over OFFLINE over
  CONNECTIONBROKEN).

Messages carry no place: an incident found from them is placed where its first evidence's
robot last was (its newest pose at or before the message; 0, 0 if it has none), and every
evidence names a message by robot and instant, placed alike. Its id digests the kind, the
robot with what tells its incidents apart (the zone, the error type, the command, the
connection) and the start.
"""

from __future__ import annotations

import bisect
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TypeVar

import msgspec

from mapservice.core.annotations import ZoneViolation
from mapservice.core.commands import CommandAcknowledged, CommandIssued, StoredCommandEvent
from mapservice.core.events import Envelope, VdaConnectionReported, VdaStateReported
from mapservice.core.incident_model import (
    OFFLINE_CRITICAL_S,
    Incident,
    IncidentThresholds,
    PoseRef,
    incident_id,
    pose_ref,
)
from mapservice.core.incidents import detect, flag_runs, presence_runs, unique_poses
from mapservice.core.liveview import OFF_STATES
from mapservice.core.ports import ConflictRow, PoseRow
from mapservice.core.vda_facts import VdaFacts

# The kinds found here (and `offline` from a connection state).
EVENT_KINDS = ("zone_violation", "conflict", "vda_error", "command_failed")
# the robot's newest pose at or before an instant, as (x, y); None if it has none
Locate = Callable[[str, int], tuple[float, float] | None]


class VdaErrorsAt(msgspec.Struct, frozen=True, gc=False):
    """A vehicle's FATAL errors at one of its states, (type, description) by type; empty
    for a state without any (one after a state with errors ends them)."""

    robot_id: str
    ts_ms: int
    fatal: tuple[tuple[str, str], ...]


class ConnectionAt(msgspec.Struct, frozen=True, gc=False):
    robot_id: str
    ts_ms: int
    state: str  # ONLINE, OFFLINE, CONNECTIONBROKEN


class EventRecords(msgspec.Struct):
    """The stored records the rules here read, of a span (any order, duplicates allowed)."""

    violations: list[ZoneViolation] = msgspec.field(default_factory=list)
    conflicts: list[ConflictRow] = msgspec.field(default_factory=list)
    vda_states: list[VdaErrorsAt] = msgspec.field(default_factory=list)
    connections: list[ConnectionAt] = msgspec.field(default_factory=list)
    commands: list[StoredCommandEvent] = msgspec.field(default_factory=list)

    def extend(self, other: EventRecords) -> None:
        self.violations += other.violations
        self.conflicts += other.conflicts
        self.vda_states += other.vda_states
        self.connections += other.connections
        self.commands += other.commands


def fatal_of(state: VdaStateReported) -> tuple[tuple[str, str], ...]:
    return tuple(sorted({(e.type, e.description) for e in state.errors if e.level == "FATAL"}))


def records_of(events: Iterable[Envelope]) -> EventRecords:
    """The records among stored events: VDA states and connection states, commands and
    their acks (violations and conflicts are findings of their own, added by the caller)."""
    out = EventRecords()
    for e in events:
        p = e.payload
        if isinstance(p, VdaStateReported):
            out.vda_states.append(VdaErrorsAt(e.robot_id, e.event_time_ms, fatal_of(p)))
        elif isinstance(p, VdaConnectionReported):
            out.connections.append(ConnectionAt(e.robot_id, e.event_time_ms, p.state))
        elif isinstance(p, CommandIssued | CommandAcknowledged):
            out.commands.append(StoredCommandEvent(e.event_time_ms, e.event_id, p))
    return out


def vda_records_of(facts: Mapping[str, VdaFacts]) -> EventRecords:
    """The VDA records of stored facts (VdaReader): a state for each instant with errors and
    each clear (the states between, without errors after one without, change nothing)."""
    out = EventRecords()
    for robot, f in facts.items():
        at: dict[int, set[tuple[str, str]]] = {t: set() for t in f.error_clears}
        for err in f.errors:
            fatal = at.setdefault(err.ts_ms, set())
            if err.level == "FATAL":
                fatal.add((err.type, err.description))
        out.vda_states += [VdaErrorsAt(robot, t, tuple(sorted(e))) for t, e in at.items()]
        out.connections += [ConnectionAt(robot, c.ts_ms, c.state) for c in f.connections]
    return out


def placed(incident: Incident, locate: Locate) -> Incident:
    """The incident with each evidence where its robot last was at its instant, and its
    place the first evidence's."""
    refs = []
    for ref in incident.evidence:
        x, y = locate(ref.robot_id, ref.ts_ms) or (0.0, 0.0)
        refs.append(PoseRef(ref.robot_id, ref.ts_ms, x, y))
    evidence = tuple(refs)
    if evidence == incident.evidence and (incident.x, incident.y) == (evidence[0].x, evidence[0].y):
        return incident
    return msgspec.structs.replace(incident, evidence=evidence, x=evidence[0].x, y=evidence[0].y)


def _message_incident(
    kind: str,
    subject: str,
    refs: Sequence[tuple[str, int]],
    robots: tuple[str, ...],
    end_ms: int,
    ongoing: bool,
    severity: str,
    measure: float,
) -> Incident:
    """An incident found from messages (`refs`, by robot and instant, the first its start),
    not placed yet (`placed` does that); `subject` tells the robot's incidents apart."""
    start = refs[0][1]
    return Incident(
        incident_id=incident_id(kind, (robots[0], subject), start),
        kind=kind,
        robots=robots,
        start_ms=start,
        end_ms=end_ms,
        ongoing=ongoing,
        x=0.0,
        y=0.0,
        severity=severity,
        measure=measure,
        evidence=tuple(PoseRef(r, t, 0.0, 0.0) for r, t in refs),
    )


# --- the rules, each over one robot's records ---------------------------------------------


def zone_violation_incidents(
    track: Sequence[PoseRow], zones: Mapping[int, str], th: IncidentThresholds
) -> list[Incident]:
    """`track`: a robot's poses as unique_poses gives them; `zones`: the zone each of its
    stored violations names, by instant (of several at one instant, the first by id)."""
    labels = [zones.get(p.ts_ms) for p in track]
    spans = presence_runs(track, th.offline_after_ms)
    incidents = []
    for zone in sorted({z for z in labels if z is not None}):
        for a, b in flag_runs([z == zone for z in labels], spans):
            robot, start, end = track[a].robot_id, track[a].ts_ms, track[b].ts_ms
            incidents.append(
                Incident(
                    incident_id=incident_id("zone_violation", (robot, zone), start),
                    kind="zone_violation",
                    robots=(robot,),
                    start_ms=start,
                    end_ms=end,
                    ongoing=b == len(track) - 1,
                    x=track[a].x,
                    y=track[a].y,
                    severity="critical",
                    measure=(end - start) / 1000,
                    evidence=(pose_ref(track[a]), pose_ref(track[b])),
                    from_data_edge=a == 0,
                )
            )
    return incidents


def zones_by_instant(violations: Iterable[ZoneViolation]) -> dict[str, dict[int, str]]:
    """robot -> instant -> zone (the first by id of the violations at that instant)."""
    out: dict[str, dict[int, str]] = defaultdict(dict)
    for v in violations:
        at = out[v.robot_id]
        at[v.ts_ms] = min(at.get(v.ts_ms, v.annotation_id), v.annotation_id)
    return out


def conflict_incidents(rows: Sequence[ConflictRow], th: IncidentThresholds) -> list[Incident]:
    """`rows`: one robot's conflicting writes (as robot_b), one per identity."""
    rows = sorted(rows, key=lambda c: (c.ts_ms, c.row, c.column, c.robot_a))
    runs: list[list[ConflictRow]] = []
    for c in rows:
        if runs and c.ts_ms - runs[-1][-1].ts_ms <= th.conflict_gap_ms:
            runs[-1].append(c)
        else:
            runs.append([c])
    incidents = []
    for run in runs:
        robot, first, last = run[0].robot_b, run[0], run[-1]
        others = tuple(sorted({c.robot_a for c in run} - {robot}))
        incidents.append(
            _message_incident(
                "conflict",
                "",
                [(robot, first.ts_ms), (first.robot_a, first.ts_a_ms), (robot, last.ts_ms)],
                robots=(robot, *others),
                end_ms=last.ts_ms,
                ongoing=False,
                severity="warning",
                measure=float(len(run)),
            )
        )
    return incidents


def vda_error_incidents(states: Sequence[VdaErrorsAt], until_ms: int) -> list[Incident]:
    """`states`: one vehicle's states, one per instant, in time order."""
    opened: dict[str, int] = {}  # error type -> the index of the state that first listed it
    incidents = []

    def found(error_type: str, first: int, end: VdaErrorsAt | None) -> None:
        robot, start = states[first].robot_id, states[first].ts_ms
        end_ms = end.ts_ms if end is not None else max(until_ms, states[-1].ts_ms)
        refs = [(robot, start)] + ([(robot, end.ts_ms)] if end is not None else [])
        incidents.append(
            _message_incident(
                "vda_error",
                error_type,
                refs,
                robots=(robot,),
                end_ms=end_ms,
                ongoing=end is None,
                severity="critical",
                measure=(end_ms - start) / 1000,
            )
        )

    for i, state in enumerate(states):
        listed = {t for t, _ in state.fatal}
        for error_type in [t for t in opened if t not in listed]:
            found(error_type, opened.pop(error_type), state)
        for error_type in sorted(listed - set(opened)):
            opened[error_type] = i
    for error_type, first in opened.items():
        found(error_type, first, None)
    return incidents


def connection_offline_incidents(states: Sequence[ConnectionAt], until_ms: int) -> list[Incident]:
    """`states`: one vehicle's connection states, one per instant, in time order."""
    incidents = []
    start: ConnectionAt | None = None

    def found(first: ConnectionAt, end: ConnectionAt | None) -> None:
        end_ms = end.ts_ms if end is not None else max(until_ms, first.ts_ms)
        off_s = (end_ms - first.ts_ms) / 1000
        refs = [(first.robot_id, first.ts_ms)] + ([(end.robot_id, end.ts_ms)] if end else [])
        incidents.append(
            _message_incident(
                "offline",
                "connection",
                refs,
                robots=(first.robot_id,),
                end_ms=end_ms,
                ongoing=end is None,
                severity="critical" if off_s >= OFFLINE_CRITICAL_S else "warning",
                measure=off_s,
            )
        )

    for state in states:
        if state.state in OFF_STATES:
            start = start or state
        elif state.state == "ONLINE" and start is not None:
            found(start, state)
            start = None
    if start is not None:
        found(start, None)
    return incidents


# An ongoing incident of these kinds (a silence, a disconnection, an error held) lasts up
# to now: its end and length are the finder's clock, not the history's, and its stored end
# is only when it was last found.
CLOCK_GROWN_KINDS = ("offline", "vda_error")


def grows_with_the_clock(incident: Incident) -> bool:
    """Whether `incident` lasts up to now (CLOCK_GROWN_KINDS, ongoing)."""
    return incident.ongoing and incident.kind in CLOCK_GROWN_KINDS


def is_connection_offline(incident: Incident) -> bool:
    """Whether an `offline` incident was found from a connection state (not a silence)."""
    return incident.kind == "offline" and incident.incident_id == incident_id(
        "offline", (incident.robots[0], "connection"), incident.start_ms
    )


def command_failed(
    issued: StoredCommandEvent,
    acks: Sequence[StoredCommandEvent],
    until_ms: int,
    th: IncidentThresholds,
) -> Incident | None:
    """A command's failure, if it failed: `acks` are the command's acks (any order)."""
    command = issued.event
    deadline = issued.ts_ms + th.command_ack_timeout_ms
    # an ack counts within the timeout of the issue (a robot's clock may run behind)
    timely = [a for a in acks if abs(a.ts_ms - issued.ts_ms) <= th.command_ack_timeout_ms]
    ack = min(timely, key=lambda a: (a.ts_ms, a.event_id), default=None)
    robot = command.robot_id
    if ack is not None:
        if not isinstance(ack.event, CommandAcknowledged) or ack.event.status != "rejected":
            return None
        end, refs = max(ack.ts_ms, issued.ts_ms), [(robot, issued.ts_ms), (robot, ack.ts_ms)]
    elif until_ms > deadline:
        end, refs = deadline, [(robot, issued.ts_ms)]
    else:
        return None
    return _message_incident(
        "command_failed",
        command.command_id,
        refs,
        robots=(robot,),
        end_ms=end,
        ongoing=False,
        severity="warning",
        measure=(end - issued.ts_ms) / 1000,
    )


def command_failed_incidents(
    commands: Iterable[StoredCommandEvent], until_ms: int, th: IncidentThresholds
) -> list[Incident]:
    issued: dict[str, StoredCommandEvent] = {}
    acks: dict[str, list[StoredCommandEvent]] = defaultdict(list)
    for c in sorted(commands, key=lambda c: (c.ts_ms, c.event_id)):
        if isinstance(c.event, CommandIssued):
            issued.setdefault(c.event.command_id, c)
        elif isinstance(c.event, CommandAcknowledged):
            acks[c.event.command_id].append(c)
    found = (command_failed(c, acks.get(k, []), until_ms, th) for k, c in issued.items())
    return [i for i in found if i is not None]


# --- the whole history ----------------------------------------------------------------------


Instant = TypeVar("Instant", VdaErrorsAt, ConnectionAt)


def by_instant(
    rows: Iterable[Instant], pick: Callable[[Instant, Instant], Instant]
) -> dict[str, list[Instant]]:
    """Each robot's rows in time order, one per instant (`pick` chooses of two)."""
    out: dict[str, dict[int, Instant]] = defaultdict(dict)
    for row in rows:
        at = out[row.robot_id]
        at[row.ts_ms] = pick(at[row.ts_ms], row) if row.ts_ms in at else row
    return {r: [at[t] for t in sorted(at)] for r, at in sorted(out.items())}


def merged_errors(a: VdaErrorsAt, b: VdaErrorsAt) -> VdaErrorsAt:
    return msgspec.structs.replace(a, fatal=tuple(sorted(set(a.fatal) | set(b.fatal))))


def later_state(a: ConnectionAt, b: ConnectionAt) -> ConnectionAt:
    return max(a, b, key=lambda c: c.state)


def unique_conflicts(rows: Iterable[ConflictRow]) -> dict[str, list[ConflictRow]]:
    """Each robot's conflicting writes (as robot_b), one per identity: the one naming the
    later A, as the store keeps them."""
    kept: dict[tuple[int, int, int, str], ConflictRow] = {}
    for c in rows:
        key = (c.ts_ms, c.row, c.column, c.robot_b)
        if key not in kept or c.ts_a_ms >= kept[key].ts_a_ms:
            kept[key] = c
    out: dict[str, list[ConflictRow]] = defaultdict(list)
    for key in sorted(kept):
        out[key[3]].append(kept[key])
    return out


def locator(tracks: Mapping[str, Sequence[PoseRow]]) -> Locate:
    def locate(robot: str, ts_ms: int) -> tuple[float, float] | None:
        track = tracks.get(robot, ())
        at = bisect.bisect_right(track, ts_ms, key=lambda p: p.ts_ms)
        return (track[at - 1].x, track[at - 1].y) if at else None

    return locate


def detect_events(
    tracks: Mapping[str, Sequence[PoseRow]],
    records: EventRecords,
    until_ms: int,
    th: IncidentThresholds,
) -> list[Incident]:
    """The incidents of the rules here, `tracks` the robots' poses as unique_poses gives
    them and `records` everything stored up to `until_ms` (later ones are left out)."""
    zones = zones_by_instant(v for v in records.violations if v.ts_ms <= until_ms)
    found: list[Incident] = []
    for robot, at in zones.items():
        found += zone_violation_incidents(tracks.get(robot, []), at, th)
    located: list[Incident] = []
    for rows in unique_conflicts(c for c in records.conflicts if c.ts_ms <= until_ms).values():
        located += conflict_incidents(rows, th)
    for states in by_instant(
        (s for s in records.vda_states if s.ts_ms <= until_ms), merged_errors
    ).values():
        located += vda_error_incidents(states, until_ms)
    for conns in by_instant(
        (c for c in records.connections if c.ts_ms <= until_ms), later_state
    ).values():
        located += connection_offline_incidents(conns, until_ms)
    located += command_failed_incidents(
        (c for c in records.commands if c.ts_ms <= until_ms), until_ms, th
    )
    locate = locator(tracks)
    return found + [placed(i, locate) for i in located]


def detect_all(
    poses: Iterable[PoseRow],
    records: EventRecords,
    until_ms: int,
    thresholds: IncidentThresholds | None = None,
) -> list[Incident]:
    """Every incident of every kind in a stored history (incidents.detect's and the rules
    here), sorted by start, kind and robots."""
    th = thresholds or IncidentThresholds()
    poses = [p for p in poses if p.ts_ms <= until_ms]
    found = detect(poses, until_ms, th)
    found += detect_events(unique_poses(poses), records, until_ms, th)
    found.sort(key=lambda i: (i.start_ms, i.kind, i.robots))
    return found
