"""The store contract, incidents (`IncidentReader`, and `append_incidents`): an incident's
latest finding replaces earlier ones whatever their insert order, retracted ones are left
out, and the reads' window, filters and order; the rules' own findings on the store's
poses come back as they were found.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py. Times are an hour ago (`t0`), inside the retention.
"""

from __future__ import annotations

import itertools
import random

import msgspec
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.incidents import Incident, PoseRef, detect, incident_id

_examples = itertools.count()


def incident(t0: int, kind="stuck", robots=("r1",), start=0, end=10_000, **more) -> Incident:
    fields = {
        "incident_id": incident_id(kind, robots, t0 + start),
        "kind": kind,
        "robots": tuple(robots),
        "start_ms": t0 + start,
        "end_ms": t0 + end,
        "ongoing": False,
        "x": 1.5,
        "y": -2.25,
        "severity": "warning",
        "measure": 30.0,
        "evidence": (PoseRef(robots[0], t0 + start, 1.5, -2.25),),
    }
    return Incident(**{**fields, **more})


def test_the_latest_finding_stays_whatever_the_insert_order(store, t0) -> None:
    first = incident(t0, end=10_000, ongoing=True)
    later = incident(t0, end=40_000, measure=60.0)
    store.append_incidents([later], t0 + 41_000)
    store.append_incidents([first], t0 + 11_000)  # an older finding, stored after
    assert store.incidents(t0, t0 + 60_000) == [later]


def test_a_retracted_incident_is_left_out_until_found_again(store, t0) -> None:
    one = incident(t0)
    store.append_incidents([one], t0 + 11_000)
    store.append_incidents([], t0 + 12_000, retracted=[one])
    assert store.incidents(t0, t0 + 60_000) == []
    store.append_incidents([one], t0 + 13_000)
    assert store.incidents(t0, t0 + 60_000) == [one]


def test_reads_meet_the_window_and_filter_by_kind_and_robot(store, t0) -> None:
    rows = [
        incident(t0, "stuck", ("r1",), 0, 10_000),
        incident(t0, "near_miss", ("r1", "r2"), 5_000, 6_000),
        incident(t0, "offline", ("r3",), 20_000, 50_000),
        incident(t0, "battery_low", ("r2",), 5_000, 5_000),
    ]
    store.append_incidents(rows, t0 + 60_000)

    def ids(*args, **kwargs):
        return [(i.kind, i.start_ms - t0) for i in store.incidents(*args, **kwargs)]

    # start < to and end >= from, by start then kind
    assert ids(t0 + 6_000, t0 + 20_000) == [("stuck", 0), ("near_miss", 5_000)]
    assert ids(t0 + 5_000, t0 + 5_001) == [
        ("stuck", 0),
        ("battery_low", 5_000),
        ("near_miss", 5_000),
    ]
    assert ids(t0 + 50_000, t0 + 60_000) == [("offline", 20_000)]
    assert ids(t0 + 50_001, t0 + 60_000) == []
    assert ids(t0, t0 + 60_000, kinds=["offline", "stuck"]) == [("stuck", 0), ("offline", 20_000)]
    assert ids(t0, t0 + 60_000, robot_id="r2") == [("battery_low", 5_000), ("near_miss", 5_000)]
    assert ids(t0, t0 + 60_000, robot_id="nobody") == []
    assert len(store.incidents(t0, t0 + 60_000, limit=3)) == 3


def test_reads_meet_the_window_at_both_ends_and_an_ongoing_silence_throughout(store, t0) -> None:
    """[from, to): an incident ended before `from` is left out, one begun before it and
    ended inside is listed, and so is an ongoing one whose stored end (where it was last
    found) lies before `from`: it has not ended."""
    rows = [
        incident(t0, "stuck", ("r1",), 0, 9_999),  # ended just before from
        incident(t0, "near_miss", ("r1", "r2"), 2_000, 10_000),  # ended just at from
        incident(t0, "battery_low", ("r2",), 5_000, 15_000),  # begun before, ended inside
        incident(t0, "offline", ("r3",), 1_000, 4_000, ongoing=True),  # silent since
        incident(t0, "stuck", ("r4",), 3_000, 5_000, ongoing=True),  # no report since
        incident(t0, "offline", ("r5",), 30_000, 40_000, ongoing=True),  # begun at to
    ]
    store.append_incidents(rows, t0 + 60_000)
    got = [(i.kind, i.robots) for i in store.incidents(t0 + 10_000, t0 + 30_000)]
    assert got == [
        ("offline", ("r3",)),
        ("near_miss", ("r1", "r2")),
        ("stuck", ("r4",)),
        ("battery_low", ("r2",)),
    ]
    assert [i.kind for i in store.incidents(t0 + 4_001, t0 + 5_000, kinds=["offline"])] == [
        "offline"
    ]


def test_an_ongoing_incident_meets_every_span_after_its_start(store, t0) -> None:
    """The live detection's restart reads an ongoing incident whatever its stored end (it
    lags: rewritten only now and then), as every read does; one that ended stays within its
    bounds, and none meets a span before its start."""
    going = incident(t0, "offline", ("r1",), 0, 10_000, ongoing=True)
    ended = incident(t0, "offline", ("r2",), 0, 10_000)
    later = incident(t0, "offline", ("r3",), 90_000, 95_000, ongoing=True)
    store.append_incidents([going, ended, later], t0 + 96_000)

    def robots(from_ms: int, to_ms: int, **kwargs) -> list[str]:
        return sorted(i.robots[0] for i in store.incidents(t0 + from_ms, t0 + to_ms, **kwargs))

    assert robots(50_000, 60_000) == ["r1"]
    assert robots(10_000, 60_000) == ["r1", "r2"]
    assert robots(10_001, 90_001) == ["r1", "r3"]
    assert robots(-5_000, 0) == []
    assert robots(50_000, 100_000, kinds=["stuck"]) == []


@settings(
    max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10_000))
def test_the_rules_findings_on_stored_poses_come_back_as_found(store, ev, t0, seed) -> None:
    """Random robots' poses stored, read back, the rules run on them, their findings stored
    and read: equal to the findings (every field, the evidence included)."""
    rng = random.Random(seed)
    base = t0 - 600_000 - seed * 1_000
    example = next(_examples)  # robots of its own: the examples share the store
    events = []
    for r in range(3):
        x, y, t = rng.uniform(0, 4), rng.uniform(0, 4), base + rng.randint(0, 999)
        for _ in range(rng.randint(20, 120)):
            t += rng.choice((1000, 1000, 500, 15_000))
            if rng.random() < 0.5:
                x, y = x + rng.uniform(-1, 1), y + rng.uniform(-1, 1)
            events.append(
                ev.pose(
                    f"c{example}-{r}",
                    t,
                    x=round(x, 3),
                    y=round(y, 3),
                    battery_level=rng.choice((10.0, 50.0)),
                )
            )
    store.append(events)
    until = max(e.event_time_ms for e in events) + 20_000
    poses = [p for p in store.poses(base, until) if p.robot_id.startswith(f"c{example}-")]
    # as stored: whether a run reached the read's start is the detection's, not the store's
    found = [msgspec.structs.replace(i, from_data_edge=False) for i in detect(poses, until)]
    assert found, "the history makes incidents"
    store.append_incidents(found, until)
    got = [i for i in store.incidents(base, until + 1) if i.robots[0].startswith(f"c{example}-")]
    assert got == sorted(found, key=lambda i: (i.start_ms, i.kind, i.incident_id))
