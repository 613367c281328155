"""Live detection equals recomputation: random floors' poses and the records beside them
(zone violations, conflicts, VDA 5050 states and connection states, commands and acks)
arrive in batches, out of order, some of them late (beyond what the trackers hold in
memory) or twice, with restarts in between (new trackers loaded from the store), some
after a downtime; what the trackers found and stored, batch by batch, is what the rules
find over the whole stored history (named cases: test_incident_restarts.py)."""

from __future__ import annotations

import random

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core import incident_tracker, near_miss
from mapservice.core.event_incident_tracker import EventIncidentTracker, is_event_incident
from mapservice.core.event_incidents import (
    EVENT_KINDS,
    detect_all,
    grows_with_the_clock,
    records_of,
)
from mapservice.core.events import Envelope, PoseReported, make_envelope
from mapservice.core.incident_model import incidents_to_load, settled
from mapservice.core.incident_tracker import IncidentTracker
from mapservice.core.incidents import Incident, IncidentThresholds, detect
from mapservice.core.ports import PoseRow
from mapservice.core.stored_rows import pose_rows_of
from mapservice.testing.memory_store import MemoryStore
from tests.mapservice.core.event_history import (
    Record,
    floor_records,
    record_time,
    store_records,
    stored_records,
    violations_of,
)
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


REFRESH_MS = IncidentTracker(lambda f, t, r: [], lambda f, t: []).refresh_ms


def normal(incidents: list[Incident]) -> list[tuple[Incident, int]]:
    """Each incident but for how long an ongoing one has lasted so far: an ongoing
    silence's (disconnection's, error's) end and length are the finder's clock, left out;
    an ongoing near miss, stuck robot or low battery is stored to the refresh step."""

    def key(i: Incident) -> tuple[Incident, int]:
        i = msgspec.structs.replace(i, from_data_edge=False)
        if grows_with_the_clock(i):
            return msgspec.structs.replace(i, end_ms=0, measure=0.0), 0
        if i.ongoing and not is_event_incident(i):
            return settled(i), i.end_ms // REFRESH_MS
        return i, 0

    return sorted((key(i) for i in incidents), key=lambda pair: pair[0].incident_id)


def arrivals(seed: int) -> list[tuple[int, list, list[Record]]]:
    """The history's poses and records as batches of one second of arrival: most within
    half a second of their time, some late by up to two minutes, some twice. A pose's zone
    violation comes with it."""
    rng = random.Random(seed)
    poses = floor_history(seed)
    t0 = min(p.ts_ms for p in poses)
    robots = sorted({p.robot_id for p in poses})
    timed: list[tuple[int, PoseRow | Record]] = []
    for item in [*poses, *floor_records(seed, robots, t0, 240)]:
        ts = item.ts_ms if isinstance(item, PoseRow) else record_time(item)
        delay = (
            rng.choice((0, 50, 200, 500)) if rng.random() > 0.06 else rng.randint(5_000, 120_000)
        )
        timed.append((ts + delay, item))
        if rng.random() < 0.05:
            timed.append((ts + delay + rng.randint(0, 30_000), item))
    timed.sort(key=lambda t: t[0])
    batches: dict[int, tuple[list, list[Record]]] = {}
    for at, item in timed:
        arrive = -(-at // 1000) * 1000
        events, records = batches.setdefault(arrive, ([], []))
        if isinstance(item, PoseRow):
            events.append(envelope(item, at))
            records += violations_of([item])
        else:
            records.append(item)
    return [(at, events, records) for at, (events, records) in sorted(batches.items())]


def with_downtimes(batches: list[tuple[int, list, list[Record]]], rng: random.Random):
    """The batches, but now and then the processors are down for 30 s to 400 s: what
    arrives meanwhile comes as one batch when they start again (restarted: True)."""
    k = 0
    while k < len(batches):
        now, events, records = batches[k]
        k += 1
        down = rng.random() < 0.02
        if down:
            now += rng.randint(30_000, 400_000)
            events, records = list(events), list(records)
            while k < len(batches) and batches[k][0] <= now:
                events, records = events + batches[k][1], records + batches[k][2]
                k += 1
        yield now, events, records, down


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 10_000), st.booleans())
def test_what_is_found_live_is_what_the_history_holds(seed, restarts, downtimes):
    check_live_equals_recomputed(seed, restarts, downtimes)


class Trackers:
    """The processors' two trackers over one store, as processors/incident_watch.py
    drives them."""

    def __init__(self, store: MemoryStore, th: IncidentThresholds) -> None:
        self.store = store

        def own(f: int, t: int) -> list[Incident]:
            return [i for i in store.incidents(f, t) if not is_event_incident(i)]

        def events(f: int, t: int) -> list[Incident]:
            return [i for i in store.incidents(f, t) if is_event_incident(i)]

        self.poses = IncidentTracker(reader(store), own, th, KEEP_MS)
        self.events = EventIncidentTracker(
            lambda f, t, r: stored_records(store, f, t, r), events, self.poses.track, th, KEEP_MS
        )

    def load(self, now: int) -> None:
        since, th = now - KEEP_MS, self.poses.th
        stored = incidents_to_load(self.store.incidents, since, now + 1, now, th)
        own = [i for i in stored if not is_event_incident(i)]
        self.poses.load(reader(self.store)(since, now + 1, None), since, own, now)
        records = stored_records(self.store, since, now + 1, None)
        self.events.load(records, since, stored, now, self.poses.tracks)
        self.write(now)

    def add(self, batch: list[Envelope], records: list[Record], now: int) -> None:
        findings = store_records(self.store, records)
        self.store.append(batch)
        poses = pose_rows_of(batch)
        self.poses.add(poses, now)
        findings.extend(records_of(r for r in records if isinstance(r, Envelope)))
        self.events.add(poses, findings, now)
        self.tick(now)
        self.poses.forget(now)
        self.events.forget(now)

    def tick(self, now: int) -> None:
        self.poses.tick(now)
        self.events.tick(now)
        self.write(now)

    def write(self, now: int) -> None:
        for tracker in (self.poses, self.events):
            found, retracted = tracker.take()
            self.store.append_incidents(found, now, retracted)


def check_live_equals_recomputed(seed: int, restarts: int, downtimes: bool = False) -> None:
    rng = random.Random(restarts)
    th = IncidentThresholds()
    store = MemoryStore()
    trackers = Trackers(store, th)
    now = 0
    batches = arrivals(seed)
    # the downtimes drawn first, then the restarts
    timeline = list(with_downtimes(batches, rng)) if downtimes else [(*b, False) for b in batches]
    for now, batch, records, down in timeline:
        if down or rng.random() < 0.03:  # a restart: new trackers, from the store
            trackers = Trackers(store, th)
            trackers.load(now)
        trackers.add(batch, records, now)
    trackers.tick(now)

    expected = detect_all(
        store.poses(0, now + 1, limit=10**9), stored_records(store, 0, now + 1, None), now, th
    )
    # (a floor's robots may stay out of the keep-out squares, its vehicles free of errors)
    assert len({i.kind for i in expected} & set(EVENT_KINDS)) >= 3
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


@pytest.mark.parametrize("robots", [1, 12, 60])
def test_a_rebuild_reads_the_store_a_few_times_whatever_the_number_of_robots(robots) -> None:
    """A rebuild (after a restart or a rebalance, on the processors' store thread) reads the
    poses before memory's span that each robot's rules look back on in one read, not a read
    per robot: at a thousand robots that was minutes, longer than the consumer's poll
    interval, so the group rebalanced and the rebuild began again. Robots that move, stand
    still with a path (stuck from before the span: its start is read from further back),
    run low and fall silent; what the rebuild finds is what the rules find over the
    history."""
    th = IncidentThresholds()
    store = MemoryStore()
    reads = []

    def read(from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        reads.append((from_ms, to_ms, robot))
        return reader(store)(from_ms, to_ms, robot)

    t0 = 1_795_255_200_000
    now = t0 + 240_000
    rnd = random.Random(robots)
    history = []
    for r in range(robots):
        x, y = 3.0 * r, round(rnd.uniform(0, 40), 1)
        kind = r % 4
        for k in range(240):
            if kind == 3 and 170 <= k < 200:
                continue  # silent for 30 s
            if kind != 1:  # robot 1 of each four stands still with a path: stuck
                x += 0.5
            battery = 10.0 if kind == 2 and k > 200 else 60.0
            history.append(fleet_pose(f"r{r:03d}", t0 + k * 1000, x, y, battery))
    store.append([envelope(p, p.ts_ms) for p in history])
    held_from = now - KEEP_MS
    # what the processors stored before the restart: every incident as the rules find it
    expected = [i for i in detect(history, now, th) if i.end_ms >= held_from - th.lookback_ms]
    tracker = IncidentTracker(read, store.incidents, th, KEEP_MS)
    tracker.load(read(held_from, now + 1, None), held_from, expected, now)
    # A robot whose own incident goes on from before what memory holds (stuck since the
    # history began) has its run read back from its start, alone: those reads follow the
    # incidents that go on that long, not the fleet.
    long_ongoing = {
        i.robots[0]
        for i in expected
        if i.ongoing and i.kind != "near_miss" and i.start_ms < t0 + 60_000
    }
    assert len(reads) <= 4 + 2 * len(long_ongoing), (len(reads), long_ongoing, reads[:8])
    found = [i for i in tracker.current.values() if i.end_ms >= held_from - th.lookback_ms]
    assert normal(found) == normal(expected)
    if robots >= 4:
        assert {i.kind for i in expected} >= {"stuck", "battery_low", "offline"}


def fleet_pose(robot: str, ts: int, x: float, y: float, battery: float) -> PoseRow:
    return PoseRow(robot, ts, x, y, 0, 0, 0, 0, 1, battery, False, None, ((0.0, 0.0),), ts)


@pytest.mark.parametrize("seed", range(4))
def test_the_live_case_judges_only_the_robots_whose_new_poses_can_start_something(
    seed, monkeypatch
) -> None:
    """Poses after each robot's newest: a robot driving on (faster than the stuck distance
    a pose, its battery fine, no silence) has no own incident to change, and its window is
    not judged again; the robots standing with a path and those running low are."""
    rng = random.Random(seed)
    th = IncidentThresholds()
    tracker = IncidentTracker(lambda f, t, r: [], lambda f, t: [], th, 120_000)
    t0 = 1_795_255_200_000
    robots = [f"r{k:02d}" for k in range(30)]
    standing = set(rng.sample(robots, 4))
    low = set(rng.sample(robots, 3))
    speed = {r: rng.uniform(0.2, 2.0) for r in robots}
    batches = [
        [
            fleet_pose(
                r,
                t0 + s * 1000 + k * 7,
                # 4 m apart across: no near misses to judge
                0.0 if r in standing else s * speed[r],
                4.0 * k,
                10.0 if r in low else 80.0,
            )
            for k, r in enumerate(robots)
        ]
        for s in range(45)
    ]
    for s, batch in enumerate(batches[:-1]):
        tracker.add(batch, t0 + (s + 1) * 1000)
        tracker.take()

    judged = []
    stuck_incidents = incident_tracker.stuck_incidents

    def counted(track, *args):
        judged.extend(p.robot_id for p in track[-1:])
        return stuck_incidents(track, *args)

    monkeypatch.setattr(incident_tracker, "stuck_incidents", counted)
    tracker.add(batches[-1], t0 + 45_000)
    assert set(judged) == standing | low
    going_on = [i for i in tracker.current.values() if i.kind == "stuck" and i.ongoing]
    assert {i.robots[0] for i in going_on} == standing
    assert all(i.end_ms >= t0 + 44_000 for i in going_on)  # to the batch's poses


@pytest.mark.parametrize("pairs", [2, 9])
def test_near_misses_going_on_are_judged_in_one_pass_whatever_their_number(
    pairs, monkeypatch
) -> None:
    """Pairs of robots driving side by side, closer than the near-miss distance: each
    batch carries their runs on, all of them in one pass over the arrays (not one per
    pair, each a fixed cost of array operations)."""
    th = IncidentThresholds()
    tracker = IncidentTracker(lambda f, t, r: [], lambda f, t: [], th, 120_000)
    t0 = 1_795_255_200_000

    def batch(s: int) -> list[PoseRow]:
        return [
            fleet_pose(f"p{k:02d}{side}", t0 + s * 1000 + k, s * 1.0, 10.0 * k + 0.5 * n, 80.0)
            for k in range(pairs)
            for n, side in enumerate("ab")
        ]

    for s in range(10):
        tracker.add(batch(s), t0 + (s + 1) * 1000)
    going_on = [i for i in tracker.current.values() if i.kind == "near_miss" and i.ongoing]
    assert len(going_on) == pairs
    passes = []
    places = near_miss._places

    def counted(*args):
        passes.append(1)
        return places(*args)

    monkeypatch.setattr(near_miss, "_places", counted)
    tracker.add(batch(10), t0 + 11_000)
    assert len(passes) == 1
    assert {i.robots for i in tracker.current.values() if i.ongoing} == {
        (f"p{k:02d}a", f"p{k:02d}b") for k in range(pairs)
    }


@pytest.mark.parametrize("seconds", [30, 240])
def test_a_near_miss_going_on_costs_each_batch_its_new_ticks_only(seconds, monkeypatch) -> None:
    """Two robots side by side for minutes (a queue at a door, a convoy): each batch
    carries their run on from the ticks it can change, so a batch costs the same at the
    run's fourth minute as at its first seconds (judged from the run's start, it cost a
    tick more every half second), and the run found is the one the rule finds."""
    th = IncidentThresholds()
    t0 = 1_795_255_200_000
    poses = [
        fleet_pose(robot, t0 + s * 1000 + k, s * 0.5, 0.4 * k, 80.0)
        for s in range(seconds + 1)
        for k, robot in enumerate(("a", "b"))
    ]
    tracker = IncidentTracker(lambda f, t, r: [], lambda f, t: [], th, 600_000)
    places = near_miss._places
    per_batch: list[int] = []

    def counted(*args):
        result = places(*args)
        per_batch.append(len(result[0]))
        return result

    monkeypatch.setattr(near_miss, "_places", counted)
    for s in range(seconds + 1):
        tracker.add(poses[2 * s : 2 * s + 2], t0 + s * 1000 + 500)
    assert max(per_batch[5:]) <= 8  # two robots, a second's ticks and its edges
    [run] = [i for i in tracker.current.values() if i.kind == "near_miss"]
    [expected] = [i for i in detect(poses, t0 + seconds * 1000 + 500, th) if i.kind == "near_miss"]
    assert normal([run]) == normal([expected])
    assert run.ongoing and run.end_ms - run.start_ms >= (seconds - 1) * 1000


@pytest.mark.parametrize("refresh_ms", [2_000, 10_000])
def test_an_incident_going_on_is_written_once_a_refresh_and_its_end_at_once(refresh_ms) -> None:
    """A robot stuck with a path, and two robots side by side, for four minutes, a batch
    every half second: each incident is written when it begins, once each time its end
    crosses a refresh step, when it changes otherwise (its closest tick), and when it
    ends, with the end the rule finds; what is stored meanwhile lags its end by less than
    a refresh (not a row every batch)."""
    th = IncidentThresholds()
    t0 = 1_795_255_200_000
    seconds = 240
    tracker = IncidentTracker(lambda f, t, r: [], lambda f, t: [], th, 600_000, refresh_ms)
    stored: dict[str, Incident] = {}
    refreshes: dict[str, int] = {}
    poses: list[PoseRow] = []
    for half in range(2 * seconds + 1):
        s, odd = divmod(half, 2)
        at = t0 + s * 1000 + 500 * odd
        # the pair drives on side by side, closest at the 30th second; at the end "b"
        # turns away; "c" stands still
        batch = [
            fleet_pose(
                robot,
                at + k,
                s * 0.5 + (5.0 if robot == "b" and half >= 470 else 0),
                y - (0.1 if robot == "b" and s == 30 else 0),
                80,
            )
            for k, (robot, y) in enumerate((("a", 0.0), ("b", 0.4), ("c", 20.0)))
            if odd == k % 2 or robot == "c"
        ]
        batch = [p if p.robot_id != "c" else fleet_pose("c", at + 2, 3.0, 20.0, 80) for p in batch]
        poses += batch
        tracker.add(batch, at + 300)
        for i in tracker.take()[0]:
            before = stored.get(i.incident_id)
            if before is not None and settled(before) == settled(i):  # lasted longer only
                refreshes[i.incident_id] = refreshes.get(i.incident_id, 0) + 1
            stored[i.incident_id] = i
        for i in tracker.current.values():
            if i.ongoing:  # never behind by a refresh
                assert i.end_ms - stored[i.incident_id].end_ms < refresh_ms
    expected = {i.incident_id: i for i in detect(poses, at + 300, th)}
    assert {i.kind for i in expected.values()} == {"near_miss", "stuck"}
    near = next(i for i in expected.values() if i.kind == "near_miss")
    assert not near.ongoing  # ended by "b" turning away: written at once, exactly
    got = stored[near.incident_id]
    assert {
        f: getattr(got, f) for f in got.__struct_fields__ if getattr(got, f) != getattr(near, f)
    } == {}
    for key, incident in expected.items():
        steps = (incident.end_ms - incident.start_ms) / refresh_ms
        assert refreshes[key] <= steps + 1  # and enough: never a refresh behind, above


@pytest.mark.parametrize("offset_ms", [0, 1, 250, 499, 500, 501])
def test_a_near_miss_carried_on_across_a_tick_on_a_newest_pose_is_the_rules(offset_ms) -> None:
    """Two robots side by side at one distance, one's poses on the ticks: a tick on a
    robot's newest pose is placed from the pose before it until the next comes, then from
    that next (the same place, the last bit aside, other evidence). The run carried on
    batch by batch is the one the rule finds over the whole history, evidence and all."""
    th = IncidentThresholds()
    t0 = 1_795_255_200_000
    tracker = IncidentTracker(lambda f, t, r: [], lambda f, t: [], th, 600_000)
    poses: list[PoseRow] = []
    for half in range(2 * 60):
        s, odd = divmod(half, 2)
        robot, y, at = ("b", 0.4, t0 + s * 1000 + offset_ms) if odd else ("a", 0.0, t0 + s * 1000)
        poses.append(fleet_pose(robot, at, s * 0.5, y, 80))
        tracker.add(poses[-1:], at + 100)
    [run] = [i for i in tracker.current.values() if i.kind == "near_miss"]
    [rule] = [i for i in detect(poses, poses[-1].ts_ms + 100, th) if i.kind == "near_miss"]
    assert msgspec.structs.replace(run, from_data_edge=False) == msgspec.structs.replace(
        rule, from_data_edge=False
    )
