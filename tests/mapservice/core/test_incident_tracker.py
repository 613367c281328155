"""Live detection equals recomputation: random floors' poses arrive in batches, out of order,
some of them late (beyond what the tracker holds in memory) or twice, with restarts in
between (a new tracker loaded from the store); what the tracker found and stored, batch
by batch, is what the rules find over the whole stored history."""

from __future__ import annotations

import random

import msgspec
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core.events import PoseReported, make_envelope
from mapservice.core.incident_tracker import IncidentTracker
from mapservice.core.incidents import Incident, IncidentThresholds, detect
from mapservice.core.ports import PoseRow
from mapservice.core.stored_rows import pose_rows_of
from mapservice.testing.memory_store import MemoryStore
from tests.mapservice.core.test_incidents import floor_history

KEEP_MS = 45_000  # short: late poses and long incidents reach beyond memory


def envelope(p: PoseRow, receive_ms: int):
    payload = PoseReported(
        position=(p.x, p.y, 0.0),
        orientation=(0.0, 0.0, 0.0, 1.0),
        battery_level=p.battery_level,
        charging=p.charging,
        path=p.path,
    )
    return make_envelope(p.robot_id, p.ts_ms, receive_ms, payload)


def reader(store: MemoryStore):
    def read(from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        newest = [p for p in store.robots_at(from_ms - 1) if robot in (None, p.robot_id)]
        return newest + store.poses(from_ms, to_ms, robot, limit=10**9)

    return read


def normal(incidents: list[Incident]) -> list[Incident]:
    """An ongoing silence's end and length are the finder's clock: left out."""
    return sorted(
        (
            msgspec.structs.replace(i, end_ms=0, measure=0.0, from_data_edge=False)
            if i.kind == "offline" and i.ongoing
            else msgspec.structs.replace(i, from_data_edge=False)
            for i in incidents
        ),
        key=lambda i: i.incident_id,
    )


def arrivals(seed: int) -> list[tuple[int, list]]:
    """The history's poses as batches of one second of arrival: most within half a second
    of their time, some late by up to two minutes, some twice."""
    rng = random.Random(seed)
    timed = []
    for p in floor_history(seed):
        delay = (
            rng.choice((0, 50, 200, 500)) if rng.random() > 0.06 else rng.randint(5_000, 120_000)
        )
        timed.append((p.ts_ms + delay, p))
        if rng.random() < 0.05:
            timed.append((p.ts_ms + delay + rng.randint(0, 30_000), p))
    timed.sort(key=lambda t: t[0])
    batches: dict[int, list] = {}
    for at, p in timed:
        arrive = -(-at // 1000) * 1000
        batches.setdefault(arrive, []).append(envelope(p, at))
    return sorted(batches.items())


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 10_000))
def test_what_is_found_live_is_what_the_history_holds(seed, restarts):
    check_live_equals_recomputed(seed, restarts)


def check_live_equals_recomputed(seed: int, restarts: int) -> None:
    rng = random.Random(restarts)
    th = IncidentThresholds()
    store = MemoryStore()
    tracker = IncidentTracker(reader(store), store.incidents, th, KEEP_MS)
    now = 0
    for now, batch in arrivals(seed):
        if rng.random() < 0.03:  # a restart: a new tracker, from the store
            tracker = IncidentTracker(reader(store), store.incidents, th, KEEP_MS)
            since = now - KEEP_MS
            tracker.load(
                reader(store)(since, now + 1, None),
                since,
                store.incidents(since - th.lookback_ms, now + 1),
                now,
            )
            found, retracted = tracker.take()
            store.append_incidents(found, now, retracted)
        store.append(batch)
        tracker.add(pose_rows_of(batch), now)
        tracker.tick(now)
        found, retracted = tracker.take()
        store.append_incidents(found, now, retracted)
        tracker.forget(now)
    tracker.tick(now)
    found, retracted = tracker.take()
    store.append_incidents(found, now, retracted)

    expected = detect(store.poses(0, now + 1, limit=10**9), now, th)
    assert expected
    assert normal(store.incidents(0, now + 1)) == normal(expected)


def test_a_batch_of_poses_older_than_memory_reads_the_store_once() -> None:
    """A backlog (poses of minutes ago, after a restart or from a robot's buffer): one read
    brings memory back to them, not a read per pose or per robot (each read is a store
    query on the processors' one store thread)."""
    th = IncidentThresholds()
    store = MemoryStore()
    reads = []

    def read(from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        reads.append((from_ms, to_ms, robot))
        return reader(store)(from_ms, to_ms, robot)

    tracker = IncidentTracker(read, store.incidents, th, KEEP_MS)
    t0 = 1_795_255_200_000
    now = t0 + 600_000
    tracker.load([], now - KEEP_MS, [], now)
    backlog = [
        envelope(
            PoseRow(
                f"r{r}",
                t0 + k * 1000,
                float(k % 7),
                float(r),
                0,
                0,
                0,
                0,
                1,
                50.0,
                False,
                None,
                None,
                t0 + k * 1000,
            ),
            now,
        )
        for r in range(20)
        for k in range(60)
    ]
    store.append(backlog)
    reads.clear()
    tracker.add(pose_rows_of(backlog), now)
    assert len(reads) <= 2, reads
