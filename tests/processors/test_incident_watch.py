"""The processors find incidents as batches are stored: what they write is what the rules
find over the stored history (stuck, near misses, low batteries, silences, a late pose
breaking one), written with the conflicts before the commit, a failed write retried, and
a rebuilt view (a restart) writes nothing it had written."""

from __future__ import annotations

import asyncio

import pytest

from mapservice.core.events import encode
from mapservice.core.incidents import detect
from mapservice.core.ports import ConflictRow
from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import HistorySink
from mapservice.settings import Settings
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from tests.processors.history_consumer_kit import NOW, POSES, Clock, live_views

PATH = ((1.0, 1.0), (9.0, 1.0))


class IncidentLog(MemoryStore):
    """Counts incident writes and fails the first `failures` of them."""

    def __init__(self, failures: int = 0) -> None:
        super().__init__()
        self.failures = failures
        self.writes: list[int] = []

    def append_incidents(self, found, found_ms, retracted=()) -> None:
        if self.failures:
            self.failures -= 1
            raise ConnectionError("clickhouse away")
        self.writes.append(len(found) + len(retracted))
        super().append_incidents(found, found_ms, retracted)


class Announced:
    """The live stream's incident announcements, as the store held them when each came."""

    def __init__(self, store: MemoryStore, fail: bool = False) -> None:
        self.store, self.fail = store, fail
        self.calls: list[tuple[list, list, int, list]] = []

    def publish_incidents(self, found, retracted, found_ms) -> None:
        self.calls.append((list(found), list(retracted), found_ms, self.store.incidents(0, 2**62)))
        if self.fail:
            raise BufferError("local queue full")


class Floor:
    """A consumer with live views on a clock the test moves (`now`), and batches of poses."""

    def __init__(self, store: IncidentLog | None = None, live: Announced | None = None) -> None:
        self.store = store or IncidentLog()
        self.live = live
        self.source, self.clock, self.now = MemorySource(), Clock(), NOW - 120_000
        self.start()

    def start(self) -> None:
        sink = HistorySink(self.store)
        self.views = live_views(
            Settings(), self.store, None, sink.thread, now_ms=lambda: self.now, live=self.live
        )
        self.views.load()
        self.consumer = HistoryConsumer(
            self.source,
            sink,
            self.views,
            batch_size=1000,
            batch_seconds=0.01,
            now_ms=lambda: self.now,
            monotonic=self.clock,
            views_seconds=0.0,
        )

    def send(self, ev, *poses: tuple) -> None:
        """Poses (robot, seconds after NOW - 120 s, x, y, battery, path), stored as one batch."""
        for robot, t_s, x, y, battery, path in poses:
            t = NOW - 120_000 + round(t_s * 1000)
            self.source.append(
                POSES, encode(ev.pose(robot, t, x, y, battery_level=battery, path=path))
            )
            self.now = max(self.now, t + 300)
        self.clock.t += 1
        asyncio.run(self.consumer.run_once())

    def tick(self, seconds: float) -> None:
        """The clock moves on; the consumer polls, waits its window and finds nothing more."""
        self.now += round(seconds * 1000)
        asyncio.run(self.consumer.run_once())
        asyncio.run(self.views.tick())
        asyncio.run(self.views.write_found_until_done())

    def expected(self):
        return detect(self.store.poses(0, self.now + 1, limit=10**9), self.now)

    def stored(self):
        return self.store.incidents(0, self.now + 1)


def _normal(incidents):
    return sorted(
        (i.kind, i.robots, i.start_ms, i.end_ms if not (i.kind == "offline" and i.ongoing) else 0)
        for i in incidents
    )


def test_what_the_processors_write_is_what_the_rules_find(ev) -> None:
    floor = Floor()
    for t in range(60):
        floor.send(
            ev,
            # s stands still with a path for 40 s; a passes b at 0.5 m; c's battery runs low
            ("s", t, 5.0 if t < 40 else 5.0 + t - 40, 5.0, 80.0, PATH),
            ("a", t, float(t) * 0.5, 0.0, 80.0, PATH),
            ("b", t, 15.0, 0.5, 80.0, None),
            ("c", t, 20.0, 20.0, 20.0 - t * 0.25, None),
        )
    kinds = {i.kind for i in floor.stored()}
    assert {"stuck", "near_miss", "battery_low"} <= kinds
    assert _normal(floor.stored()) == _normal(floor.expected())
    # the clock moves on with no more poses: every robot falls silent
    floor.tick(11)
    assert {i.robots for i in floor.stored() if i.kind == "offline" and i.ongoing} == {
        ("s",),
        ("a",),
        ("b",),
        ("c",),
    }


def test_a_late_pose_retracts_the_silence_it_fills(ev) -> None:
    floor = Floor()
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(10)])
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(25, 35)])
    assert [i.kind for i in floor.stored()] == ["offline"]
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(10, 25, 2)])
    assert floor.stored() == []
    assert _normal(floor.stored()) == _normal(floor.expected())


def test_a_failed_write_is_retried_and_a_restart_writes_nothing_again(ev) -> None:
    store = IncidentLog(failures=1)
    floor = Floor(store)
    floor.send(ev, *[("s", t, 3.0, 3.0, 5.0, PATH) for t in range(40)])
    found = floor.stored()
    assert sorted(i.kind for i in found) == ["battery_low", "stuck"]
    writes = len(store.writes)
    floor.start()  # a restart: the views rebuilt from the store
    asyncio.run(floor.views.write_found_until_done())
    assert len(store.writes) == writes
    assert floor.stored() == found


@pytest.mark.parametrize("feed_fails", [False, True])
def test_each_stored_finding_is_announced_once_after_it_is_stored(ev, feed_fails) -> None:
    """Every write of findings is announced once, after the store holds them (a live page
    asking the list then gets them too), with its retractions; a write that failed is
    announced when its retry succeeds, and a feed that fails loses the announcement only
    (the findings stay stored, the processors go on)."""
    store = IncidentLog(failures=1)
    live = Announced(store, fail=feed_fails)
    floor = Floor(store, live)
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(10)])
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(25, 35)])
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(10, 25, 2)])
    floor.tick(11)
    assert len(live.calls) == len(store.writes) >= 3
    found_ids: set[str] = set()
    for found, retracted, found_ms, stored_then in live.calls:
        held = {i.incident_id: i for i in stored_then}
        assert all(held.get(i.incident_id) == i for i in found)
        assert not {i.incident_id for i in retracted} & set(held)
        assert found_ms <= floor.now
        found_ids |= {i.incident_id for i in found}
        found_ids -= {i.incident_id for i in retracted}
    # What the announcements add up to is what the store lists.
    assert found_ids == {i.incident_id for i in floor.stored()}
    assert [i.kind for i in floor.stored()] == ["offline"]


@pytest.mark.parametrize("behind_s", [12, 30, 120])
def test_a_replica_behind_the_stream_finds_silent_only_the_robots_the_stream_shows_silent(
    ev, behind_s
) -> None:
    """A backlog read late (after a restart, or a replica slower than the fleet for a
    while): 20 robots' poses every second, each batch stored `behind_s` after the gateway
    received it, and one robot falling silent halfway. Judged by the wall clock every robot
    would be silent (offline in the fleet, an `offline` incident and an alert each); judged
    by the stream as far as it is stored, only the one that fell silent is. Once a poll
    finds nothing more to read, the wall clock judges: everyone has fallen silent."""
    floor = Floor()
    robots = [f"r{k:02d}" for k in range(20)]
    for t in range(60):
        floor.now = NOW - 120_000 + (t + behind_s) * 1000  # when the batch is read
        floor.send(
            ev,
            *[
                (r, t, 3.0 * k, 0.5 * t, 80.0, None)
                for k, r in enumerate(robots)
                if r != "r00" or t < 30
            ],
        )
        asyncio.run(floor.views.tick())
        asyncio.run(floor.views.write_found_until_done())
    assert floor.views.presence.online == set(robots) - {"r00"}
    assert [i.robots for i in floor.stored() if i.kind == "offline"] == [("r00",)]
    # a poll that may not wait (after a long store) and comes back empty proves nothing
    floor.now += 5_000  # (behind by 12 s or more: everyone silent by the wall clock)
    floor.clock.t += 5
    asyncio.run(floor.consumer.run_once())
    asyncio.run(floor.views.tick())
    assert floor.views.presence.online == set(robots) - {"r00"}
    floor.tick(6)  # the consumer finds nothing more: caught up, and the floor is quiet
    assert floor.views.presence.online == set()
    assert {i.robots for i in floor.stored() if i.kind == "offline"} == {(r,) for r in robots}


def test_a_store_failing_in_a_tick_fails_that_tick_only_and_keeps_what_it_was_to_judge(
    ev, monkeypatch
) -> None:
    """The once-a-second tick reads the store (placing conflicts, silences): a store that
    fails meanwhile (restarting) must not raise out of the app's timer (it would crash the
    app, and its snapshot and retention timers with it), and the conflicts that tick was
    to judge are judged by the next."""
    floor = Floor()
    floor.send(ev, ("a", 0, 1.0, 1.0, 80.0, None), ("b", 0, 2.0, 1.0, 80.0, None))
    watch = floor.views.incidents
    conflict = ConflictRow(0, 0, NOW - 120_000, "a", NOW - 125_000, "b")
    watch.stored_conflicts([conflict])

    def away(*args, **kwargs):
        raise ConnectionError("clickhouse restarting")

    monkeypatch.setattr(watch.events, "add", away)
    asyncio.run(floor.views.tick())
    assert watch.unplaced.conflicts == [conflict]
    monkeypatch.undo()
    floor.tick(1)
    assert [i.kind for i in floor.stored() if i.kind == "conflict"] == ["conflict"]
    assert watch.unplaced.conflicts == []


def test_a_restart_loads_every_stored_incident_of_its_span_however_many() -> None:
    """More incidents in the memory span than one read's limit (a busy plant's near
    misses): the reads ordered by start were cut at 10,000, dropping the newest, those a
    restart most needs (the one still going on, here)."""
    from mapservice.core.incident_model import SEVERITIES, PoseRef, incident_id
    from mapservice.core.incidents import Incident

    def near_miss(start_ms: int, ongoing: bool) -> Incident:
        robots = ("a", "b")
        return Incident(
            incident_id=incident_id("near_miss", robots, start_ms),
            kind="near_miss",
            robots=robots,
            start_ms=start_ms,
            end_ms=start_ms + 1,
            ongoing=ongoing,
            x=1.0,
            y=1.0,
            severity=SEVERITIES[0],
            measure=0.4,
            evidence=(PoseRef("a", start_ms, 1.0, 1.0), PoseRef("b", start_ms + 1, 1.4, 1.0)),
        )

    floor = Floor()
    first = NOW - 60_000
    many = [near_miss(first + k, ongoing=False) for k in range(12_000)]
    last = near_miss(first + 40_000, ongoing=True)
    floor.store.append_incidents([*many, last], NOW - 1_000)
    watch = floor.views.incidents
    stored = watch.stored_incidents(first, NOW)
    assert len(stored) == 12_001 and stored[-1] == last
    floor.start()  # the restart's load keeps the ongoing one
    assert last.incident_id in floor.views.incidents.tracker.current
