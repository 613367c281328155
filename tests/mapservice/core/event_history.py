"""Random histories of the records the event incidents are found from (beside a floor's
poses): zone violations of the poses in two keep-out squares, conflicting writes, VDA 5050
states with FATAL errors and connection states, commands with acks, rejections and
silences; and the records a store holds, read back."""

from __future__ import annotations

import random
from collections.abc import Sequence

from mapservice.core.annotations import ZoneViolation
from mapservice.core.commands import CommandAcknowledged, CommandIssued
from mapservice.core.event_incidents import EventRecords
from mapservice.core.events import (
    Envelope,
    VdaConnectionReported,
    VdaError,
    VdaStateReported,
    make_envelope,
)
from mapservice.core.ports import ConflictRow, PoseRow
from mapservice.processors.incident_watch import EventSources
from mapservice.testing.memory_store import MemoryStore

# A stored record: an event (VDA state, connection, command, ack), or a finding of the views
Record = Envelope | ZoneViolation | ConflictRow


def zone_of(p: PoseRow) -> str | None:
    """Two keep-out squares of the floor (what zone_watch finds, by a simpler rule)."""
    if p.x < 1.5 and p.y < 1.5:
        return "keep-a"
    if p.x > 4.5 and p.y > 4.5:
        return "keep-b"
    return None


def violations_of(poses: Sequence[PoseRow]) -> list[ZoneViolation]:
    return [
        ZoneViolation(p.ts_ms, p.robot_id, zone, p.x, p.y)
        for p in poses
        if (zone := zone_of(p)) is not None
    ]


def vda_state(robot: str, ts: int, errors: Sequence[tuple[str, str]]) -> Envelope:
    state = VdaStateReported(
        "acme",
        robot,
        "2.0.0",
        None,
        None,
        False,
        None,
        None,
        None,
        None,
        None,
        "AUTOMATIC",
        "",
        tuple(VdaError(level, kind) for level, kind in errors),
    )
    return make_envelope(robot, ts, ts, state)


def connection(robot: str, ts: int, state: str) -> Envelope:
    return make_envelope(robot, ts, ts, VdaConnectionReported("acme", robot, "2.0.0", state, ts))


def issue(robot: str, ts: int, command_id: str) -> Envelope:
    return make_envelope(robot, ts, ts, CommandIssued(command_id, robot, "pause", "op", ts))


def ack(robot: str, ts: int, command_id: str, status: str) -> Envelope:
    return make_envelope(robot, ts, ts, CommandAcknowledged(command_id, robot, status))


def record_time(r: Record) -> int:
    return r.event_time_ms if isinstance(r, Envelope) else r.ts_ms


def floor_records(seed: int, robots: Sequence[str], t0: int, seconds: int) -> list[Record]:
    """Records of `robots` over `seconds` from `t0` (zone violations come with the poses)."""
    rng = random.Random(seed * 7919 + 1)
    out: list[Record] = []
    vehicles = rng.sample(list(robots), min(2, len(robots)))
    for robot in vehicles:
        t = t0 + rng.randint(0, 3000)
        errors: list[tuple[str, str]] = []
        while t < t0 + seconds * 1000:
            if rng.random() < 0.25:
                errors = [
                    (rng.choice(("FATAL", "FATAL", "WARNING")), rng.choice(("e1", "e2", "e3")))
                    for _ in range(rng.randint(0, 2))
                ]
            out.append(vda_state(robot, t, errors))
            t += rng.choice((1000, 1000, 2000, 5000, 30_000))
        t = t0
        while t < t0 + seconds * 1000:
            out.append(connection(robot, t, rng.choice(("ONLINE", "OFFLINE", "CONNECTIONBROKEN"))))
            t += rng.randint(1000, 90_000)
    for k in range(rng.randint(3, 12)):
        robot, t = rng.choice(robots), t0 + rng.randint(0, seconds * 1000)
        out.append(issue(robot, t, f"c{k}"))
        for _ in range(rng.choice((0, 1, 1, 2))):
            delay = rng.choice((0, 500, 9_999, 10_000, 10_001, 30_000, -200))
            out.append(ack(robot, t + delay, f"c{k}", rng.choice(("accepted", "rejected"))))
    for _ in range(rng.randint(2, 15)):
        b, a = rng.sample(list(robots), 2) if len(robots) > 1 else (robots[0], robots[0])
        t = t0 + rng.randint(0, seconds * 1000)
        for chunk in range(rng.randint(1, 3)):
            out.append(ConflictRow(chunk, chunk % 2, t, a, t - rng.randint(0, 60_000), b))
    return out


def store_records(store: MemoryStore, records: Sequence[Record]) -> EventRecords:
    """Stores `records` as the processors do; returns the findings among them (the views
    give those to the incident watch, the events it reads itself)."""
    events = [r for r in records if isinstance(r, Envelope)]
    violations = [r for r in records if isinstance(r, ZoneViolation)]
    conflicts = [r for r in records if isinstance(r, ConflictRow)]
    store.append(events)
    store.append_zone_violations(violations)
    store.append_conflicts(conflicts)
    return EventRecords(violations=violations, conflicts=conflicts)


def stored_records(store: MemoryStore, from_ms: int, to_ms: int, robot: str | None) -> EventRecords:
    """The records stored in [from_ms, to_ms), as the processors read them back."""
    return EventSources(store, store, store, store).read(from_ms, to_ms, robot)
