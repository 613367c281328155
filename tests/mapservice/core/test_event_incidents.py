"""The rules of the incidents found from stored records (zone violations, conflicts, VDA 5050
errors and connection states, commands), each just inside and just outside its thresholds,
and their answers independent of the order and the duplicates of the records."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core.annotations import ZoneViolation
from mapservice.core.event_incidents import (
    EventRecords,
    detect_all,
    is_connection_offline,
    records_of,
)
from mapservice.core.incidents import Incident, IncidentThresholds
from mapservice.core.ports import ConflictRow
from tests.mapservice.core.event_history import ack, connection, issue, vda_state
from tests.mapservice.core.test_incidents import T0, kinds, pose

TH = IncidentThresholds()


def at(seconds: float) -> int:
    return T0 + round(seconds * 1000)


def found(records: EventRecords, poses=(), until_s: float = 600.0, th=TH) -> list[Incident]:
    return detect_all(list(poses), records, at(until_s), th)


# zone_violation ------------------------------------------------------------------------


def inside(robot: str, seconds: list[float], zone: str = "keep-a") -> list[ZoneViolation]:
    return [ZoneViolation(at(t), robot, zone, 1.0, 1.0) for t in seconds]


@pytest.mark.parametrize(
    ("gap_ms", "runs"),
    [(TH.offline_after_ms, 1), (TH.offline_after_ms + 1, 2)],  # a silence splits at once
)
def test_a_robot_in_a_zone_is_one_incident_until_a_silence(gap_ms, runs) -> None:
    poses = [pose(t_s=t, x=1.0, y=1.0) for t in (0, 1, 2)]
    poses.append(pose(t_s=2 + gap_ms / 1000, x=1.0, y=1.0))
    records = EventRecords(violations=inside("r1", [p.ts_ms / 1000 - T0 / 1000 for p in poses]))
    zone = kinds(found(records, poses, until_s=20), "zone_violation")
    assert len(zone) == runs
    assert zone[0].start_ms == at(0) and zone[-1].end_ms == poses[-1].ts_ms
    assert zone[-1].ongoing and zone[0].severity == "critical"


def test_a_pose_outside_or_in_another_zone_ends_the_run() -> None:
    poses = [pose(t_s=t, x=1.0, y=1.0) for t in range(6)]
    records = EventRecords(
        violations=inside("r1", [0, 1]) + inside("r1", [3]) + inside("r1", [4, 5], "keep-b")
    )
    zone = kinds(found(records, poses, until_s=6), "zone_violation")
    assert [(i.start_ms, i.end_ms, i.ongoing) for i in zone] == [
        (at(0), at(1), False),
        (at(3), at(3), False),
        (at(4), at(5), True),
    ]
    assert zone[0].measure == 1.0
    assert len({i.incident_id for i in zone}) == 3


# conflict ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("gap_ms", "incidents"), [(TH.conflict_gap_ms, 1), (TH.conflict_gap_ms + 1, 2)]
)
def test_one_robots_conflicting_writes_within_the_gap_are_one_incident(gap_ms, incidents) -> None:
    rows = [
        ConflictRow(3, 4, at(10), "r2", at(5), "r1"),
        ConflictRow(3, 5, at(10), "r2", at(5), "r1"),
        ConflictRow(3, 4, at(10) + gap_ms, "r3", at(9), "r1"),
    ]
    conflicts = kinds(found(EventRecords(conflicts=rows), [pose(t_s=9, x=2.0, y=3.0)]), "conflict")
    assert len(conflicts) == incidents
    first = conflicts[0]
    assert first.robots[0] == "r1" and not first.ongoing and first.severity == "warning"
    assert (first.x, first.y) == (2.0, 3.0)  # where the robot last was
    if incidents == 1:
        assert first.robots == ("r1", "r2", "r3") and first.measure == 3
    else:
        assert first.robots == ("r1", "r2") and first.measure == 2


# vda_error -----------------------------------------------------------------------------


def test_a_fatal_error_holds_from_the_state_that_lists_it_to_the_first_without() -> None:
    states = [
        vda_state("v1", at(0), []),
        vda_state("v1", at(1), [("WARNING", "w")]),  # not fatal
        vda_state("v1", at(2), [("FATAL", "e1")]),
        vda_state("v1", at(3), [("FATAL", "e1"), ("FATAL", "e2")]),
        vda_state("v1", at(4), [("FATAL", "e2"), ("WARNING", "e1")]),
        vda_state("v1", at(5), [("FATAL", "e2")]),
    ]
    errors = kinds(found(records_of(states)), "vda_error")
    assert [(i.start_ms, i.end_ms, i.ongoing) for i in errors] == [
        (at(2), at(4), False),  # e1: ended by the state listing it as a warning
        (at(3), at(600), True),  # e2: still listed by the newest state, up to now
    ]
    assert {i.severity for i in errors} == {"critical"} and errors[0].measure == 2.0


# command_failed ------------------------------------------------------------------------

TIMEOUT = TH.command_ack_timeout_ms


@pytest.mark.parametrize(
    ("delay_ms", "status", "failed"),
    [
        (TIMEOUT, "accepted", None),  # just in time
        (TIMEOUT + 1, "accepted", "timeout"),  # just late
        (TIMEOUT, "rejected", "rejected"),
        (TIMEOUT + 1, "rejected", "timeout"),
        (-TIMEOUT, "accepted", None),  # a robot's clock behind
        (-TIMEOUT - 1, "accepted", "timeout"),
        (None, None, "timeout"),
    ],
)
def test_a_command_fails_when_refused_or_not_acknowledged_in_time(delay_ms, status, failed) -> None:
    events = [issue("r1", at(10), "c1")]
    if delay_ms is not None:
        events.append(ack("r1", at(10) + delay_ms, "c1", status))
    incidents = kinds(found(records_of(events)), "command_failed")
    if failed is None:
        assert not incidents
        return
    (incident,) = incidents
    assert incident.start_ms == at(10) and incident.severity == "warning"
    if failed == "rejected":
        assert incident.end_ms == at(10) + delay_ms and len(incident.evidence) == 2
    else:
        assert incident.end_ms == at(10) + TIMEOUT and incident.measure == TIMEOUT / 1000


@pytest.mark.parametrize(("after_ms", "judged"), [(0, False), (1, True)])
def test_a_silence_of_acks_is_judged_once_the_history_is_known_past_the_deadline(
    after_ms, judged
) -> None:
    records = records_of([issue("r1", at(10), "c1")])
    until = 10 + (TIMEOUT + after_ms) / 1000
    assert bool(kinds(found(records, until_s=until), "command_failed")) == judged


# offline from a connection state -------------------------------------------------------


@pytest.mark.parametrize("state", ["OFFLINE", "CONNECTIONBROKEN"])
def test_a_vehicle_is_offline_from_its_connection_state_until_it_is_online(state) -> None:
    events = [
        connection("v1", at(0), "ONLINE"),
        connection("v1", at(5), state),
        connection("v1", at(6), "OFFLINE"),  # still the same incident
        connection("v1", at(20), "ONLINE"),
        connection("v1", at(30), state),
    ]
    offline = kinds(found(records_of(events), until_s=40), "offline")
    assert [(i.start_ms, i.end_ms, i.ongoing) for i in offline] == [
        (at(5), at(20), False),
        (at(30), at(40), True),  # up to when the history is known
    ]
    assert all(is_connection_offline(i) for i in offline)


@pytest.mark.parametrize(("off_s", "severity"), [(299.999, "warning"), (300, "critical")])
def test_a_disconnection_turns_critical_after_five_minutes(off_s, severity) -> None:
    events = [connection("v1", at(0), "OFFLINE"), connection("v1", at(off_s), "ONLINE")]
    (incident,) = kinds(found(records_of(events), until_s=off_s), "offline")
    assert incident.severity == severity and incident.measure == off_s


def test_of_states_at_one_instant_online_counts() -> None:
    events = [connection("v1", at(5), "OFFLINE"), connection("v1", at(5), "ONLINE")]
    assert not kinds(found(records_of(events)), "offline")


def test_a_silence_and_a_disconnection_are_two_offline_incidents() -> None:
    poses = [pose("v1", t_s=t) for t in (0, 1, 30)]
    events = [connection("v1", at(1.5), "OFFLINE"), connection("v1", at(29), "ONLINE")]
    offline = kinds(found(records_of(events), poses, until_s=30), "offline")
    assert sorted(is_connection_offline(i) for i in offline) == [False, True]


# places and orders ---------------------------------------------------------------------


def test_an_incident_of_messages_is_placed_where_its_robot_last_was() -> None:
    poses = [pose("v1", t_s=1, x=4.0, y=2.0), pose("v1", t_s=3, x=7.0, y=2.0)]
    events = [vda_state("v1", at(2), [("FATAL", "e1")]), vda_state("v1", at(3), [])]
    (error,) = kinds(found(records_of(events), poses), "vda_error")
    assert (error.x, error.y) == (4.0, 2.0)
    assert [(e.ts_ms, e.x) for e in error.evidence] == [(at(2), 4.0), (at(3), 7.0)]
    (unplaced,) = kinds(found(records_of(events)), "vda_error")  # no pose: 0, 0
    assert (unplaced.x, unplaced.y) == (0.0, 0.0)


def vehicle_history(seed: int) -> tuple[list, EventRecords]:
    rng = random.Random(seed)
    poses = [pose("v1", t_s=t, x=rng.uniform(0, 3), y=1.0) for t in range(0, 120, 2)]
    events = []
    for t in range(0, 120, 3):
        errors = [("FATAL", rng.choice(("e1", "e2")))] if rng.random() < 0.4 else []
        events.append(vda_state("v1", at(t), errors))
        if rng.random() < 0.2:
            events.append(connection("v1", at(t + 1), rng.choice(("ONLINE", "OFFLINE"))))
        if rng.random() < 0.2:
            events.append(issue("v1", at(t), f"c{t}"))
            events.append(ack("v1", at(t + rng.randint(0, 15)), f"c{t}", "rejected"))
    records = records_of(events)
    records.violations = inside("v1", [t for t in range(0, 120, 2) if rng.random() < 0.5])
    records.conflicts = [ConflictRow(1, 1, at(t), "r9", at(t - 1), "v1") for t in range(0, 120, 7)]
    return poses, records


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.randoms(use_true_random=False))
def test_the_same_incidents_whatever_the_order_and_duplicates_of_the_records(seed, rng) -> None:
    poses, records = vehicle_history(seed)
    expected = found(records, poses, until_s=130)
    assert {i.kind for i in expected} >= {"zone_violation", "conflict"}
    shuffled = EventRecords()
    for name in ("violations", "conflicts", "vda_states", "connections", "commands"):
        rows = list(getattr(records, name))
        rows += rng.sample(rows, len(rows) // 3)
        rng.shuffle(rows)
        setattr(shuffled, name, rows)
    assert found(shuffled, poses, until_s=130) == expected
