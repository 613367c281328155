"""The shift simulator's incidents on purpose: over seeded simulated spans each behaviour
happens, a few times an hour for five robots, and crosses its threshold by a margin, as the
rules (mapservice/core/incidents.py) find it over what the robots reported."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace

import pytest

from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.incident_model import IncidentThresholds
from mapservice.core.incidents import detect
from mapservice.core.ports import PoseRow
from mapservice.core.stored_rows import pose_rows_of
from mapservice.local.demo_history import simulate
from mapservice.robot import DEFAULT_MAP, sim
from mapservice.robot.sim_incidents import for_incidents

END_MS = 1_795_255_200_000
HOURS = 3
OWN_KINDS = ("stuck", "offline", "battery_low")


@pytest.fixture(scope="module")
def floor():
    return load_ros_map(DEFAULT_MAP)


def found(floor, seed: int, th: IncidentThresholds) -> list:
    start = END_MS - HOURS * 3_600_000
    rows = [
        row
        for _, events in simulate(floor, 5, start, END_MS, seed=seed, thresholds=th)
        for row in pose_rows_of(events)
    ]
    return detect(rows, END_MS, th)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_each_behaviour_happens_at_a_floors_rate_and_crosses_its_threshold(floor, seed) -> None:
    th = IncidentThresholds()
    incidents = found(floor, seed, th)
    per_hour = {k: n / HOURS for k, n in Counter(i.kind for i in incidents).items()}
    for kind in (*OWN_KINDS, "near_miss"):
        assert per_hour.get(kind, 0) > 0, f"no {kind} in {HOURS} h: {per_hour}"
    for kind in OWN_KINDS:
        assert per_hour[kind] <= 12, f"a storm of {kind}: {per_hour}"
    # a late charge goes well below the line (a robot queueing for a charger may dip below it)
    lows = [i.measure for i in incidents if i.kind == "battery_low"]
    assert min(lows) <= 0.9 * th.battery_low_percent, lows
    for i in incidents:
        if i.kind == "stuck":
            assert i.measure >= 1.3 * th.stuck_ms / 1000, i
        elif i.kind == "offline":
            assert i.measure >= 1.5 * th.offline_after_ms / 1000, i


@pytest.mark.parametrize("seed", [5, 6])
def test_the_behaviours_follow_the_thresholds_they_are_given(floor, seed) -> None:
    """Other thresholds: the stalls, silences and late charges cross those instead."""
    th = IncidentThresholds(stuck_ms=60_000, offline_after_ms=25_000, battery_low_percent=10.0)
    incidents = found(floor, seed, th)
    kinds = {i.kind for i in incidents}
    assert {"stuck", "offline", "battery_low"} <= kinds
    assert all(i.measure >= 84 for i in incidents if i.kind == "stuck")
    assert all(i.measure >= 37.5 for i in incidents if i.kind == "offline")
    assert min(i.measure for i in incidents if i.kind == "battery_low") <= 9


def test_live_steps_stall_on_the_route_and_fall_silent(floor) -> None:
    """At the live simulator's one-second steps: a stalled robot reports the same place with
    its route for the whole stall; a silent one reports nothing, then goes on."""
    th = IncidentThresholds()
    config = for_incidents(sim.SimConfig(change_every_s=0), th)
    state = sim.new_state(floor, 5, seed=11, config=config)
    seen: dict[str, list] = {}
    stalls: list[float] = []
    for _ in range(3 * 3600):
        before = {r.robot_id: r for r in state.robots}
        state, out = sim.step(state)
        for robot in state.robots:
            if robot.stall_s > 0 and before[robot.robot_id].stall_s <= 0:
                stalls.append(robot.stall_s + config.dt_s)
        for pose in out.poses:
            seen.setdefault(pose.robot_id, []).append(pose)
    lo, hi = config.stall_s
    assert stalls and all(lo <= s <= hi for s in stalls)
    gaps = [
        (b.t_ms - a.t_ms) / 1000
        for track in seen.values()
        for a, b in zip(track, track[1:], strict=False)
        if b.t_ms - a.t_ms > 1000
    ]
    assert gaps and all(g > th.offline_after_ms / 1000 * 1.4 for g in gaps)
    still = [
        run
        for track in seen.values()
        for run in _still_with_route(track)
        if run > th.stuck_ms / 1000
    ]
    assert len(still) >= len(stalls) - 5  # a stall may still go on at the end


def _still_with_route(track) -> list[float]:
    """Seconds of each run of poses at one place with a route."""
    runs, first = [], None
    for a, b in zip(track, track[1:], strict=False):
        if b.path and (a.x, a.y) == (b.x, b.y):
            first = a if first is None else first
        else:
            if first is not None:
                runs.append((a.t_ms - first.t_ms) / 1000)
            first = None
    return runs


def test_robots_give_way_and_stations_stand_apart(floor) -> None:
    """Robots wait for each other where routes cross and stations and chargers stand apart:
    fewer near misses than robots driving through each other (head-on in an aisle they
    still pass close: their routes run down its middle), on stations spaced out."""
    th = IncidentThresholds()
    config = for_incidents(sim.SimConfig(change_every_s=0), th)
    state = sim.new_state(floor, 5, seed=3, config=config)
    places = [*state.stations, *state.chargers]
    assert all(
        math.dist(a, b) * config.cell_m >= config.station_spacing_m
        for i, a in enumerate(places)
        for b in places[i + 1 :]
    )

    def near_misses(config) -> int:
        state = sim.new_state(floor, 5, seed=3, config=config)
        rows = []
        for _ in range(2400):
            state, out = sim.step(state)
            rows += [
                PoseRow(
                    p.robot_id,
                    p.t_ms,
                    p.x,
                    p.y,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    1.0,
                    p.battery,
                    p.charging,
                    p.loaded,
                    p.path or None,
                    p.t_ms,
                )
                for p in out.poses
            ]
        return sum(1 for i in detect(rows, state.t_ms, th) if i.kind == "near_miss")

    giving_way = near_misses(config)
    driving_through = near_misses(replace(config, give_way_m=0.0, station_spacing_m=0.0))
    assert giving_way < 0.85 * driving_through, (giving_way, driving_through)
