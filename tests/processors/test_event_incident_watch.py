"""The processors find the incidents of the records stored beside the poses as batches are
stored: VDA 5050 errors and disconnections, commands refused or left without an ack (judged
by the clock), what they write is what the rules find over the stored history, and a
restart writes nothing it had written."""

from __future__ import annotations

import asyncio

from mapservice.core.event_incidents import detect_all, grows_with_the_clock
from mapservice.core.events import encode
from tests.mapservice.core.event_history import ack, connection, issue, stored_records, vda_state
from tests.processors.history_consumer_kit import NOW, POSES
from tests.processors.test_incident_watch import Floor

T0 = NOW - 120_000


def send(floor: Floor, ev, seconds: int, *events) -> None:
    """A second of a driving robot's poses and vehicle `v`'s, with `events`, as one batch."""
    t = T0 + seconds * 1000
    for robot, y in (("r", 0.0), ("v", 5.0)):
        floor.source.append(POSES, encode(ev.pose(robot, t, float(seconds), y)))
    for e in events:
        floor.source.append(POSES, encode(e))
    floor.now = max(floor.now, t + 300)
    floor.clock.t += 1
    asyncio.run(floor.consumer.run_once())


def expected(floor: Floor):
    store = floor.store
    poses = store.poses(0, floor.now + 1, limit=10**9)
    return detect_all(poses, stored_records(store, 0, floor.now + 1, None), floor.now)


def normal(incidents):
    return sorted(
        (i.incident_id, i.kind, i.robots, i.start_ms, 0 if grows_with_the_clock(i) else i.end_ms)
        for i in incidents
    )


def at(seconds: float) -> int:
    return T0 + round(seconds * 1000)


def test_vehicle_errors_disconnections_and_failed_commands_are_found_and_stored(ev) -> None:
    floor = Floor()
    for s in range(40):
        events = {
            2: [issue("r", at(2), "refused"), connection("v", at(2), "ONLINE")],
            3: [ack("r", at(3), "refused", "rejected"), issue("r", at(3), "unanswered")],
            5: [issue("r", at(5), "obeyed"), vda_state("v", at(5), [("FATAL", "lift")])],
            6: [ack("r", at(6), "obeyed", "accepted"), vda_state("v", at(6), [("FATAL", "lift")])],
            9: [vda_state("v", at(9), [("WARNING", "lift")])],
            20: [connection("v", at(20), "CONNECTIONBROKEN")],
            30: [connection("v", at(30), "ONLINE")],
        }.get(s, [])
        send(floor, ev, s, *events)
        floor.tick(0)
    stored = floor.stored()
    found = {(i.kind, i.start_ms) for i in stored}
    assert {
        ("command_failed", at(2)),  # refused
        ("command_failed", at(3)),  # no ack within the timeout
        ("vda_error", at(5)),
        ("offline", at(20)),
    } <= found
    assert ("command_failed", at(5)) not in found
    assert normal(stored) == normal(expected(floor))
    writes = len(floor.store.writes)
    floor.start()  # a restart: the views rebuilt from the store
    asyncio.run(floor.views.write_found_until_done())
    assert len(floor.store.writes) == writes


def test_a_command_left_without_an_ack_fails_when_the_clock_passes_its_deadline(ev) -> None:
    floor = Floor()
    send(floor, ev, 0, issue("r", at(0), "c1"))
    floor.tick(0)
    assert not [i for i in floor.stored() if i.kind == "command_failed"]
    floor.now = at(10) + 1  # just past the deadline, no batch since
    floor.tick(0)
    (failed,) = [i for i in floor.stored() if i.kind == "command_failed"]
    assert failed.end_ms == at(10) and failed.robots == ("r",)
    # its ack, in time by the robot's clock but stored late, retracts it
    send(floor, ev, 11, ack("r", at(9.5), "c1", "accepted"))
    assert not [i for i in floor.stored() if i.kind == "command_failed"]


def test_a_disconnection_from_before_a_restart_turns_critical_after_it(ev) -> None:
    """A vehicle's connection breaks, and the processors stop before it has lasted five
    minutes; they start again (the views rebuilt from the store) after its stored end lags
    by more than their memory: the disconnection is loaded all the same, and turns
    critical with the clock, as the rules over the stored history say."""
    floor = Floor()
    for s in range(15):
        send(floor, ev, s, *([connection("v", at(10), "CONNECTIONBROKEN")] if s == 10 else []))
        floor.tick(0)
    [broken] = [i for i in floor.stored() if i.start_ms == at(10)]
    assert broken.ongoing and broken.severity == "warning"
    floor.now = at(10 + 400)  # the processors were down
    floor.start()
    floor.tick(0)
    [broken] = [i for i in floor.stored() if i.start_ms == at(10)]
    assert broken.ongoing and broken.severity == "critical"
    assert normal(floor.stored()) == normal(expected(floor))
