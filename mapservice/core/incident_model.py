"""What an incident is (mapservice/core/incidents.py finds them): its kinds, the thresholds
of the rules, the record of one, its id, and whether it can still grow."""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import msgspec


class Placed(Protocol):
    """A pose as the rules read it: a stored pose row is one (the ports, which name this
    module's Incident, are not imported here: no circle)."""

    @property
    def robot_id(self) -> str: ...
    @property
    def ts_ms(self) -> int: ...
    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...


# The first four are found from the poses (incidents.py), the others from the messages and
# findings stored beside them (event_incidents.py; `offline` also from a vehicle's connection).
KINDS = (
    "near_miss",
    "stuck",
    "offline",
    "battery_low",
    "zone_violation",
    "conflict",
    "vda_error",
    "command_failed",
)
SEVERITIES = ("warning", "critical")
STUCK_CRITICAL_S = 300  # stood still this long: critical
OFFLINE_CRITICAL_S = 300  # silent or disconnected this long: critical


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
    # a command without an ack this long after it was issued failed
    command_ack_timeout_ms: int = 10_000
    # one robot's conflicting writes no further apart than this are one conflict incident
    conflict_gap_ms: int = 60_000

    def __post_init__(self) -> None:
        for name in ("near_miss_m", "stuck_m", "battery_low_percent"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.moving_m_s < 0:
            raise ValueError("moving_m_s must not be negative")
        for name in ("stuck_ms", "offline_after_ms", "tick_ms", "command_ack_timeout_ms"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive")
        if self.conflict_gap_ms < 0:
            raise ValueError("conflict_gap_ms must not be negative")

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
    # (stuck), silent or disconnected (offline), inside the zone (zone_violation), the error
    # held (vda_error) or waited for the ack (command_failed), the lowest level in percent
    # (battery_low), the conflicting chunk writes (conflict).
    measure: float
    evidence: tuple[PoseRef, ...]
    # The run began at the first pose the rule was given: it may reach further back than the
    # history read (a recomputation reads further back for these).
    from_data_edge: bool = False


# Kinds whose figure and last piece of evidence follow an ongoing run's end: the seconds
# stopped (to the newest pose) or silent (to the clock).
GROWING_KINDS = ("stuck", "offline")


def settled(incident: Incident) -> Incident:
    """The incident without what grows while it goes on: an ongoing one's end, and for a
    stuck or silent robot the length and the newest pose that follow it. Two findings of an
    incident that settle alike differ only in how long it has lasted so far."""
    if not incident.ongoing:
        return incident
    if incident.kind in GROWING_KINDS:
        return msgspec.structs.replace(
            incident, end_ms=0, measure=0.0, evidence=incident.evidence[:1]
        )
    return msgspec.structs.replace(incident, end_ms=0)


def meets(incident: Incident, from_ms: int, to_ms: int) -> bool:
    """Whether `incident` meets [from_ms, to_ms): begun before its end and not ended before
    its start; an ongoing one has not ended (its end is only where it was last found: a
    silence's grows with the clock, a run's waits for the robot's next pose)."""
    return incident.start_ms < to_ms and (incident.end_ms >= from_ms or incident.ongoing)


def can_still_grow(incident: Incident, now_ms: int, th: IncidentThresholds) -> bool:
    """Whether what comes after `now_ms` may still extend the incident, so that the live
    detection holds it, and what it is judged from, whatever its end: an ongoing one (its
    stored end lags: it is written again only now and then, never while the processors are
    down), or a conflict run that a conflict within the gap would join (never ongoing, but
    judged again from its start). Every such incident ends at or after
    `still_growing_from(now_ms, th)` or is ongoing."""
    return incident.ongoing or (
        incident.kind == "conflict" and incident.end_ms >= still_growing_from(now_ms, th)
    )


def still_growing_from(now_ms: int, th: IncidentThresholds) -> int:
    """The earliest end of an incident that can still grow and is not ongoing."""
    return now_ms - th.conflict_gap_ms


def incidents_to_load(
    read: Callable[[int, int], list[Incident]],
    held_from_ms: int,
    until_ms: int,
    now_ms: int,
    th: IncidentThresholds,
) -> list[Incident]:
    """What a restart of the live detection loads (its memory holding the history from
    `held_from_ms` on): the stored incidents meeting that span from a lookback before it, as
    the rules look back, and every one that can still grow, whatever its stored end. `read`:
    (from_ms, to_ms) -> the stored incidents meeting [from_ms, to_ms), an ongoing one whatever
    its stored end (IncidentReader.incidents)."""
    span_from = held_from_ms - th.lookback_ms
    stored = read(min(span_from, still_growing_from(now_ms, th)), until_ms)
    return [i for i in stored if i.end_ms >= span_from or can_still_grow(i, now_ms, th)]


def incident_id(kind: str, robots: Sequence[str], start_ms: int) -> str:
    return _incident_id(kind, tuple(robots), start_ms)


# The live detection names an ongoing incident again with every batch.
@functools.lru_cache(maxsize=65_536)
def _incident_id(kind: str, robots: tuple[str, ...], start_ms: int) -> str:
    key = "\x1f".join((kind, *robots, str(start_ms)))
    return hashlib.blake2b(key.encode(), digest_size=16).hexdigest()


def pose_ref(pose: Placed) -> PoseRef:
    return PoseRef(pose.robot_id, pose.ts_ms, pose.x, pose.y)


def distance(a: Placed, b: Placed) -> float:
    return math.hypot(a.x - b.x, a.y - b.y)


def mm2(a: Placed, b: Placed) -> int:
    """The squared distance in whole millimetres (positions are stored to the millimetre):
    exact, so a robot that moved exactly the threshold is judged alike on every machine."""
    dx, dy = round((a.x - b.x) * 1000), round((a.y - b.y) * 1000)
    return dx * dx + dy * dy
