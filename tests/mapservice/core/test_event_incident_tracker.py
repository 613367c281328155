"""The live detection of the event incidents in the live case: a robot standing in a
keep-out zone for longer than memory holds is carried on batch by batch from memory, not
read again from the store, and its run is the one the rules find."""

from __future__ import annotations

from mapservice.core.event_incident_tracker import EventIncidentTracker
from mapservice.core.event_incidents import EventRecords, detect_all
from mapservice.core.incident_tracker import IncidentTracker
from mapservice.core.incidents import IncidentThresholds
from mapservice.core.ports import ConflictRow, PoseRow
from mapservice.testing.memory_store import MemoryStore
from tests.mapservice.core.event_history import stored_records, violations_of
from tests.mapservice.core.test_incident_tracker import envelope, normal, reader

T0 = 1_795_255_200_000


def test_a_robot_standing_in_a_zone_for_long_is_carried_on_from_memory() -> None:
    th, keep_ms = IncidentThresholds(), 120_000
    store = MemoryStore()
    reads: list[tuple[int, int, str | None]] = []

    def read(from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        reads.append((from_ms, to_ms, robot))
        return reader(store)(from_ms, to_ms, robot)

    poses = IncidentTracker(read, lambda f, t: [], th, keep_ms)
    events = EventIncidentTracker(
        lambda f, t, r: stored_records(store, f, t, r), lambda f, t: [], poses.track, th, keep_ms
    )
    poses.load([], T0, [], T0)
    events.load(EventRecords(), T0, [], T0)
    late_reads = 0
    for s in range(600):
        now = T0 + s * 1000 + 500
        pose = PoseRow("r", T0 + s * 1000, 1.0, 1.0, 0, 0, 0, 0, 1, 80.0, False, None, None, now)
        batch = [envelope(pose, now)]
        violations = violations_of([pose])
        store.append(batch)
        store.append_zone_violations(violations)
        poses.add([pose], now)
        events.add([pose], EventRecords(violations=violations), now)
        for tracker in (poses, events):
            found, retracted = tracker.take()
            store.append_incidents(found, now, retracted)
        poses.forget(now)
        events.forget(now)
        if s > 300:
            late_reads += len(reads)
        reads.clear()
    assert late_reads == 0
    [going] = [i for i in store.incidents(0, now + 1) if i.kind == "zone_violation"]
    expected = detect_all(
        store.poses(0, now + 1, limit=10**9), stored_records(store, 0, now + 1, None), now, th
    )
    assert normal([going]) == normal([i for i in expected if i.kind == "zone_violation"])
    assert going.ongoing and going.start_ms == T0 and going.measure == 599.0


def test_a_conflict_run_that_goes_on_is_placed_from_memory() -> None:
    """Two robots' writes contradict each other every 5 s for ten minutes: one conflict
    incident that grows. Each batch judges it again from its start, whose records and
    evidence lie before memory's span: the run's records stay in memory while a conflict
    may still extend it, and its places are kept from the known incident, not read and
    located again from the store each batch (a query a batch per such robot, growing with the
    history: half of `serve`'s CPU at 20 robots in an hour's soak). The run is the one
    the rules find over the history."""
    th, keep_ms = IncidentThresholds(), 120_000
    store = MemoryStore()
    reads: list[tuple[int, int, str | None]] = []

    def read(from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        reads.append((from_ms, to_ms, robot))
        return reader(store)(from_ms, to_ms, robot)

    poses = IncidentTracker(read, lambda f, t: [], th, keep_ms)

    def read_records(from_ms: int, to_ms: int, robot: str | None) -> EventRecords:
        reads.append((from_ms, to_ms, robot))
        return stored_records(store, from_ms, to_ms, robot)

    events = EventIncidentTracker(read_records, lambda f, t: [], poses.track, th, keep_ms)
    poses.load([], T0, [], T0)
    events.load(EventRecords(), T0, [], T0)
    late_reads = 0
    for s in range(600):
        now = T0 + s * 1000 + 500
        ts = T0 + s * 1000
        batch_poses = [
            PoseRow(r, ts, x, 1.0 + s * 0.01, 0, 0, 0, 0, 1, 80.0, False, None, None, now)
            for r, x in (("a", 1.0), ("b", 4.0))
        ]
        conflicts = [ConflictRow(3, 4, ts, "a", ts - 1000, "b")] if s % 5 == 4 else []
        store.append([envelope(p, now) for p in batch_poses])
        store.append_conflicts(conflicts)
        poses.add(batch_poses, now)
        events.add(batch_poses, EventRecords(conflicts=conflicts), now)
        for tracker in (poses, events):
            found, retracted = tracker.take()
            store.append_incidents(found, now, retracted)
        poses.forget(now)
        events.forget(now)
        if s > 300:
            late_reads += len(reads)
        reads.clear()
    assert late_reads == 0
    [going] = [i for i in store.incidents(0, now + 1) if i.kind == "conflict"]
    expected = detect_all(
        store.poses(0, now + 1, limit=10**9), stored_records(store, 0, now + 1, None), now, th
    )
    assert normal([going]) == normal([i for i in expected if i.kind == "conflict"])
    assert going.start_ms == T0 + 4000 and going.measure == 120
