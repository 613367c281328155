"""Live detection equals recomputation across restarts, named: histories the random ones of
test_incident_tracker.py once found differing, and the constructed ones behind them. A
restart loads what can still grow whatever its stored end (an ongoing incident's lags), a
retraction not yet stored does not let the store bring the incident back, and what memory
read from the store lacks (a VDA state without errors that a late one turns into the end
of an error) is read again."""

from __future__ import annotations

import pytest

from mapservice.core.event_incidents import detect_all, is_connection_offline
from mapservice.core.incident_model import can_still_grow, incidents_to_load
from mapservice.core.incidents import Incident, IncidentThresholds, PoseRef, incident_id
from mapservice.testing.memory_store import MemoryStore
from tests.mapservice.core.event_history import connection, stored_records, vda_state
from tests.mapservice.core.test_incident_tracker import (
    KEEP_MS,
    Trackers,
    check_live_equals_recomputed,
    envelope,
    fleet_pose,
    normal,
)

T0 = 1_795_255_200_000


def at(seconds: float) -> int:
    return T0 + round(seconds * 1000)


def assert_as_recomputed(store: MemoryStore, now: int, th: IncidentThresholds) -> None:
    expected = detect_all(
        store.poses(0, now + 1, limit=10**9), stored_records(store, 0, now + 1, None), now, th
    )
    assert normal(store.incidents(0, now + 1)) == normal(expected)


@pytest.mark.parametrize(
    ("seed", "restarts", "downtimes"),
    [
        # a disconnection stored before a restart whose stored end lagged beyond memory
        pytest.param(754, 616, False, id="disconnection-going-on-across-a-restart"),
        # a late FATAL state before a state without errors that memory, read from the
        # store, lacked
        pytest.param(1262, 2796, False, id="late-error-before-a-state-without-errors"),
        # a retracted error read back from the store before its retraction was stored
        pytest.param(1576, 9114, False, id="retracted-error-read-back"),
        # after a downtime: a disconnection retracted, read back before that was stored
        pytest.param(18, 2545, True, id="downtime-retracted-disconnection-read-back"),
        # after a downtime: a near miss loaded with its stored end, behind the new ticks
        pytest.param(50, 5928, True, id="downtime-near-miss-stored-behind-its-end"),
    ],
)
def test_histories_that_once_differed(seed, restarts, downtimes) -> None:
    check_live_equals_recomputed(seed, restarts, downtimes)


@pytest.mark.parametrize(
    ("began", "after_restart", "restart_s", "ongoing", "severity"),
    [
        # the vehicle's connection drops and stays down past the critical length
        pytest.param("disconnected", None, 320, True, "critical", id="turns-critical"),
        # it comes back after the restart: the disconnection ends there
        pytest.param(
            "disconnected",
            connection("v", T0 + 210_000, "ONLINE"),
            200,
            False,
            "warning",
            id="reconnects",
        ),
        # a FATAL error held from before the restart, cleared after it
        pytest.param(
            "fatal error", vda_state("v", T0 + 210_000, []), 200, False, "critical", id="cleared"
        ),
    ],
)
def test_an_incident_going_on_from_long_before_a_restart_is_judged_again_after_it(
    began, after_restart, restart_s, ongoing, severity
) -> None:
    """A vehicle falls silent (its poses stop, its connection drops or a FATAL error
    holds): the incidents are stored, and rewritten now and then while they go on. The
    processors stop, and start again (new trackers, loaded from the store) after the stored
    end lags by more than memory holds and its lookback: the disconnection's or error's
    records lie before memory, but it can still grow, so it is loaded and judged again. It
    turns critical, or ends, as the rules over the whole stored history say (loaded only
    when it met memory's span, it kept its warning severity and never ended)."""
    th = IncidentThresholds()
    store = MemoryStore()
    trackers = Trackers(store, th)
    trackers.load(T0)
    first = connection("v", T0 + 1_000, "OFFLINE")
    if began == "fatal error":
        first = vda_state("v", T0 + 1_000, [("FATAL", "e1")])
    pose = fleet_pose("v", T0, 1.0, 1.0, 80.0)
    trackers.add([envelope(pose, T0 + 500)], [first], T0 + 1_500)
    trackers.tick(T0 + 100_000)  # written again while it goes on, then the processors stop
    [stored] = [i for i in store.incidents(0, T0 + 1_000_000) if i.start_ms == T0 + 1_000]
    now = T0 + restart_s * 1000
    assert stored.ongoing and stored.end_ms < now - KEEP_MS - th.lookback_ms
    trackers = Trackers(store, th)
    trackers.load(now)
    if after_restart is not None:
        now += 11_000
        trackers.add([], [after_restart], now)
    trackers.tick(now)

    [going] = [i for i in store.incidents(0, now + 1) if i.start_ms == T0 + 1_000]
    assert (going.ongoing, going.severity) == (ongoing, severity)
    expected = detect_all(
        store.poses(0, now + 1, limit=10**9), stored_records(store, 0, now + 1, None), now, th
    )
    assert normal(store.incidents(0, now + 1)) == normal(expected)


def test_a_restart_loads_what_meets_memory_and_every_incident_that_can_still_grow() -> None:
    """incidents_to_load: the incidents meeting memory's span from a lookback before it;
    an ongoing one whatever its stored end; a conflict run that a conflict within the gap
    may extend (just inside the gap: loaded, just outside: not)."""
    th = IncidentThresholds(conflict_gap_ms=600_000)  # longer than memory and its lookback
    store = MemoryStore()
    now, held_from = T0 + 3_600_000, T0 + 3_600_000 - KEEP_MS
    span_from = held_from - th.lookback_ms

    def incident(kind: str, robot: str, end_ms: int, ongoing: bool = False) -> Incident:
        start = end_ms - 5_000
        return Incident(
            incident_id(kind, (robot,), start),
            kind,
            (robot,),
            start,
            end_ms,
            ongoing,
            0.0,
            0.0,
            "warning",
            1.0,
            (PoseRef(robot, start, 0.0, 0.0),),
        )

    loaded = {
        "in memory's lookback": incident("stuck", "a", span_from),
        "ongoing, stored an hour ago": incident("offline", "b", T0, ongoing=True),
        "conflict, just inside the gap": incident("conflict", "c", now - th.conflict_gap_ms),
    }
    left = {
        "before the lookback": incident("stuck", "d", span_from - 1),
        "conflict, just outside the gap": incident("conflict", "e", now - th.conflict_gap_ms - 1),
        "offline, ended an hour ago": incident("offline", "f", T0),
    }
    store.append_incidents([*loaded.values(), *left.values()], now - 1)
    got = incidents_to_load(store.incidents, held_from, now + 1, now, th)
    assert sorted(i.robots[0] for i in got) == ["a", "b", "c"]
    assert can_still_grow(loaded["conflict, just inside the gap"], now, th)
    assert not can_still_grow(left["conflict, just outside the gap"], now, th)


def test_an_incident_retracted_but_not_yet_stored_is_not_read_back_from_the_store() -> None:
    """A vehicle's connection breaks at 10 s (an ongoing disconnection, stored). Minutes
    later an earlier break, at 5 s, comes late with a pose placing it: the disconnection
    starts at 5 s, and the one from 10 s is retracted. The store holds that one until the
    retraction is written, and placing the late pose's incidents reads the store: it must
    not bring it back (two disconnections went on, the rules find one)."""
    th = IncidentThresholds()
    store = MemoryStore()
    trackers = Trackers(store, th)
    trackers.load(T0)
    trackers.add([envelope(fleet_pose("v", T0, 1.0, 1.0, 80.0), at(0.5))], [], at(0.5))
    trackers.add([], [connection("v", at(10), "OFFLINE")], at(10.5))
    trackers.add([], [], at(150))  # memory lets go of the first minutes
    now = at(200)
    late = fleet_pose("v", at(4), 1.0, 1.0, 80.0)
    trackers.add([envelope(late, now)], [connection("v", at(5), "CONNECTIONBROKEN")], now)
    broken = [i for i in store.incidents(0, now + 1) if is_connection_offline(i)]
    assert [(i.start_ms, i.ongoing) for i in broken] == [(at(5), True)]
    assert_as_recomputed(store, now, th)


def test_a_near_miss_stored_behind_its_end_before_a_restart_ends_after_it() -> None:
    """Two robots drive side by side, 0.4 m apart, for nine seconds; then "b" falls silent
    while "a" drives on. The near miss goes on (b's newest pose is in it) and is stored
    behind its end (written again once a refresh). The processors stop, and start again
    minutes later: "b" comes back elsewhere, so the run ended with b's last pose there.
    Loaded with its stored end, before the ticks the new poses change, it must be judged
    again all the same (it went on, ongoing, for ever)."""
    th = IncidentThresholds()
    store = MemoryStore()
    trackers = Trackers(store, th)
    trackers.load(T0)
    for s in range(21):
        poses = [fleet_pose("a", at(s), 0.5 * s, 0.0, 80.0)]
        if s < 10:
            poses.append(fleet_pose("b", at(s) + 1, 0.5 * s, 0.4, 80.0))
        trackers.add([envelope(p, at(s + 0.5)) for p in poses], [], at(s + 0.5))
    [near] = [i for i in store.incidents(0, at(30)) if i.kind == "near_miss"]
    assert near.ongoing and near.end_ms < at(8)  # stored behind its end
    now = at(300)
    trackers = Trackers(store, th)
    trackers.load(now)
    back = [fleet_pose("b", at(s), 50.0, 50.0, 80.0) for s in (290, 291)]
    trackers.add([envelope(p, now) for p in back], [], now)
    [near] = [i for i in store.incidents(0, now + 1) if i.kind == "near_miss"]
    assert not near.ongoing and near.end_ms == at(9)
    assert_as_recomputed(store, now, th)


def test_a_late_fatal_error_after_a_restart_ends_at_the_next_state_without_errors() -> None:
    """A vehicle's states without errors at 10, 12 and 20 s: the store keeps the states
    with errors and those after one (the others change nothing), so the trackers loaded
    after a restart hold none of them. A state with a FATAL error at 11 s comes late: the
    state at 12 s now ends it, and is read again (the error did not go on to 20 s)."""
    th = IncidentThresholds()
    store = MemoryStore()
    trackers = Trackers(store, th)
    trackers.load(T0)
    for s in (10, 12, 20):
        trackers.add([], [vda_state("v", at(s), [])], at(s + 0.5))
    now = at(21)
    trackers = Trackers(store, th)
    trackers.load(now)
    trackers.add([], [vda_state("v", at(11), [("FATAL", "e1")])], at(22))
    [error] = [i for i in store.incidents(0, at(23)) if i.kind == "vda_error"]
    assert (error.start_ms, error.end_ms, error.ongoing) == (at(11), at(12), False)
    assert_as_recomputed(store, at(22), th)
