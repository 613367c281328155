"""The incident rules on constructed histories: each kind just inside and just outside each
of its thresholds, and the rules' answers independent of the order, the duplicates and the
span the history is read in."""

from __future__ import annotations

import bisect
import math
import random

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core.incident_model import mm2
from mapservice.core.incidents import (
    Incident,
    IncidentThresholds,
    detect,
    incident_id,
    is_charging,
    near_miss_incidents,
    stuck_possible_at,
    unique_poses,
)
from mapservice.core.near_miss import near_misses, pose_columns
from mapservice.core.ports import PoseRow
from tests.mapservice.core.near_miss_reference import (
    near_miss_incidents as reference_near_misses,
)

T0 = 1_795_255_200_000
TH = IncidentThresholds()
PATH = ((5.0, 5.0), (9.0, 5.0))


def pose(robot="r1", t_s=0.0, x=0.0, y=0.0, *, battery=None, charging=None, path=PATH):
    ts = T0 + round(t_s * 1000)
    return PoseRow(robot, ts, x, y, 0.0, 0.0, 0.0, 0.0, 1.0, battery, charging, None, path, ts)


def kinds(incidents: list[Incident], kind: str) -> list[Incident]:
    return [i for i in incidents if i.kind == kind]


def until(poses: list[PoseRow]) -> int:
    """Just after the newest pose: no silence at the end."""
    return max(p.ts_ms for p in poses)


# stuck -------------------------------------------------------------------------------


def stopped(seconds: int, drift_m: float, *, moving_before_s: int = 5, path=PATH):
    """A robot driving at 1 m/s, then standing (drifting `drift_m` in all) for `seconds`,
    then driving on; one pose a second."""
    poses = [pose(t_s=t, x=float(t)) for t in range(moving_before_s)]
    x0 = float(moving_before_s)
    for k in range(seconds + 1):
        poses.append(pose(t_s=moving_before_s + k, x=x0 + drift_m * k / seconds, path=path))
    end = moving_before_s + seconds
    poses += [pose(t_s=end + k, x=x0 + drift_m + k) for k in range(1, 4)]
    return poses


@pytest.mark.parametrize(
    ("seconds", "drift_m", "found"),
    [
        (30, 0.0, True),
        (29, 0.0, False),  # just shorter than the window
        (30, 0.099, True),  # just inside the distance
        (30, 0.1, False),  # the distance is strict
        (30, 0.101, False),
        (120, 0.05, True),
    ],
)
def test_stuck_just_inside_and_outside_its_window_and_distance(seconds, drift_m, found):
    poses = stopped(seconds, drift_m)
    stuck = kinds(detect(poses, until(poses)), "stuck")
    assert bool(stuck) == found
    if found:
        (incident,) = stuck
        assert incident.start_ms == T0 + 5_000  # when it stopped
        assert incident.end_ms == T0 + (5 + seconds) * 1000
        assert incident.measure == seconds
        assert not incident.ongoing


def test_a_robot_without_a_path_standing_still_is_not_stuck():
    poses = stopped(60, 0.0, path=None) + stopped(60, 0.0, path=())
    assert not kinds(detect(poses, until(poses)), "stuck")


def test_a_silence_inside_the_window_is_not_standing_still():
    # 20 s still, 11 s silent (offline), 20 s still at the same place: never 30 s observed
    poses = [pose(t_s=t) for t in range(20)] + [pose(t_s=31 + t) for t in range(20)]
    found = detect(poses, until(poses))
    assert not kinds(found, "stuck")
    assert len(kinds(found, "offline")) == 1


# battery_low -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("level", "charging", "found"),
    [
        (14.99, None, True),
        (15.0, None, False),
        (0.0, False, True),
        (3.0, "false", True),
        (3.0, True, False),
        (3.0, "true", False),
        (None, None, False),
    ],
)
def test_battery_low_below_its_level_and_not_charging(level, charging, found):
    poses = [pose(t_s=t, x=t, battery=50.0) for t in range(3)]
    poses += [pose(t_s=3 + t, x=3 + t, battery=level, charging=charging) for t in range(5)]
    poses += [pose(t_s=8, x=8, battery=50.0, charging=True)]
    low = kinds(detect(poses, until(poses)), "battery_low")
    assert bool(low) == found
    if found:
        (incident,) = low
        assert (incident.start_ms, incident.end_ms) == (T0 + 3000, T0 + 7000)
        assert incident.measure == level
        assert incident.severity == ("critical" if level < 5 else "warning")


@pytest.mark.parametrize("word", ["true", "TRUE", " yes", "1", "charging"])
def test_charging_words(word):
    assert is_charging(word) and not is_charging("false") and not is_charging(None)


# offline -----------------------------------------------------------------------------


@pytest.mark.parametrize(("silence_s", "found"), [(10.0, False), (10.001, True), (40.0, True)])
def test_offline_after_a_silence_longer_than_its_threshold(silence_s, found):
    poses = [pose(t_s=0), pose(t_s=1), pose(t_s=1 + silence_s), pose(t_s=2 + silence_s)]
    offline = kinds(detect(poses, until(poses)), "offline")
    assert bool(offline) == found
    if found:
        (incident,) = offline
        assert (incident.start_ms, incident.end_ms) == (
            T0 + 1000,
            T0 + round((1 + silence_s) * 1000),
        )
        assert not incident.ongoing


@pytest.mark.parametrize(("silent_ms", "found"), [(10_000, False), (10_001, True)])
def test_offline_up_to_now_is_ongoing(silent_ms, found):
    poses = [pose(t_s=0), pose(t_s=1)]
    offline = kinds(detect(poses, T0 + 1000 + silent_ms), "offline")
    assert bool(offline) == found
    if found:
        assert offline[0].ongoing and offline[0].end_ms == T0 + 1000 + silent_ms


# near_miss ---------------------------------------------------------------------------


def crossing(gap_m: float, speed_m_s: float = 1.0, *, other_moving: bool = False):
    """r1 drives along y=0 at `speed_m_s` past r2, parked at (10, gap_m)."""
    poses = [pose("r1", t, x=speed_m_s * t) for t in range(round(20 / speed_m_s) + 1)]
    poses += [pose("r2", t, x=10.0 + (0.01 * t if other_moving else 0), y=gap_m) for t in range(21)]
    return poses


@pytest.mark.parametrize(
    ("gap_m", "found"), [(0.999, True), (1.0, False), (1.001, False), (0.3, True)]
)
def test_near_miss_just_inside_and_outside_its_distance(gap_m, found):
    poses = crossing(gap_m)
    near = kinds(detect(poses, until(poses)), "near_miss")
    assert bool(near) == found
    if found:
        (incident,) = near
        assert incident.robots == ("r1", "r2")
        assert incident.measure == pytest.approx(gap_m, abs=1e-3)
        assert (incident.x, incident.y) == pytest.approx((10.0, gap_m / 2))
        assert incident.start_ms <= T0 + 10_000 <= incident.end_ms
        assert incident.severity == ("critical" if gap_m < 0.5 else "warning")


@pytest.mark.parametrize(("speed", "found"), [(0.05, False), (0.051, True), (0.0, False)])
def test_near_miss_needs_one_of_them_moving(speed, found):
    # both creep side by side 0.5 m apart
    poses = [pose("r1", t, x=round(speed * t, 4)) for t in range(10)]
    poses += [pose("r2", t, x=round(speed * t, 4), y=0.5) for t in range(10)]
    assert bool(kinds(detect(poses, until(poses)), "near_miss")) == found


def test_near_miss_positions_are_interpolated_between_unsynchronised_poses():
    # r1's poses on whole seconds, r2's on half seconds: they meet between their poses
    r1 = [pose("r1", t, x=float(t)) for t in range(21)]
    r2 = [pose("r2", t + 0.5, x=20.0 - (t + 0.5), y=0.4) for t in range(20)]
    (incident,) = kinds(detect(r1 + r2, until(r1 + r2)), "near_miss")
    assert incident.measure == pytest.approx(0.4, abs=1e-3)
    assert incident.x == pytest.approx(10.0)


def test_no_position_across_a_silence():
    # r1 jumps 20 m over a 30 s silence: no interpolated pass by r2 on the way
    poses = [pose("r1", 0, x=0.0), pose("r1", 30, x=20.0)]
    poses += [pose("r2", t, x=10.0) for t in range(31)]
    assert not kinds(detect(poses, until(poses)), "near_miss")


# ids and histories --------------------------------------------------------------------


def test_an_incident_is_named_by_its_kind_robots_and_start():
    assert incident_id("stuck", ("r1",), 5) == incident_id("stuck", ["r1"], 5)
    ids = {
        incident_id(k, r, s) for k in ("stuck", "offline") for r in (("a",), ("b",)) for s in (1, 2)
    }
    assert len(ids) == 8


def test_of_two_poses_at_one_instant_the_last_given_stays_as_in_the_store():
    first = pose(t_s=1, x=1.0)
    second = msgspec.structs.replace(first, x=9.0, receive_time_ms=first.receive_time_ms - 5)
    assert unique_poses([first, second])["r1"] == [second]
    assert unique_poses([second, first])["r1"] == [first]


def floor_history(seed: int) -> list[PoseRow]:
    """A few robots on a small floor for a few minutes: driving, standing, crossing, falling
    silent, their batteries running down and charging."""
    rng = random.Random(seed)
    poses = []
    for r in range(rng.randint(2, 5)):
        robot = f"r{r}"
        x, y, heading = rng.uniform(0, 6), rng.uniform(0, 6), rng.uniform(0, math.tau)
        battery, t = rng.uniform(5, 40), rng.uniform(0, 3)
        while t < 240:
            mode = rng.random()
            for _ in range(rng.randint(3, 45)):
                t += rng.choice((1.0, 1.0, 1.0, 0.5, 1.5)) if mode > 0.05 else rng.uniform(8, 25)
                if mode < 0.6:
                    heading += rng.uniform(-0.4, 0.4)
                    step = rng.uniform(0.2, 1.2)
                    x = min(6.0, max(0.0, x + step * math.cos(heading)))
                    y = min(6.0, max(0.0, y + step * math.sin(heading)))
                elif mode < 0.8:
                    x, y = x + rng.uniform(-0.02, 0.02), y + rng.uniform(-0.02, 0.02)
                charging = mode > 0.9
                battery = min(100.0, max(0.0, battery + (2 if charging else -0.2)))
                poses.append(
                    pose(
                        robot,
                        round(t, 3),
                        round(x, 3),
                        round(y, 3),
                        battery=round(battery, 1),
                        charging=charging,
                        path=PATH if mode < 0.85 else None,
                    )
                )
    return poses


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.randoms(use_true_random=False))
def test_the_same_incidents_whatever_the_order_and_duplicates_of_the_poses(seed, rng):
    poses = floor_history(seed)
    now = max(p.ts_ms for p in poses) + rng.randint(0, 20_000)
    expected = detect(poses, now)
    shuffled = poses + rng.sample(poses, len(poses) // 3)
    rng.shuffle(shuffled)
    assert detect(shuffled, now) == expected


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(30, 200))
def test_a_span_read_with_its_lookback_finds_what_the_whole_history_finds(seed, from_s):
    """Recomputing a span from the history since `lookback_ms` before it (and each robot's
    last pose before that) gives the whole history's incidents that start in the span,
    except those the rules flag as reaching back to the data's edge."""
    poses = floor_history(seed)
    now = max(p.ts_ms for p in poses) + 5_000
    span_from = T0 + from_s * 1000
    read_from = span_from - TH.lookback_ms
    tracks = unique_poses(poses)
    before = [
        max((p for p in track if p.ts_ms < read_from), key=lambda p: p.ts_ms)
        for track in tracks.values()
        if track[0].ts_ms < read_from
    ]
    read = before + [p for p in poses if p.ts_ms >= read_from]
    whole = {i.incident_id: i for i in detect(poses, now) if i.start_ms >= span_from}
    part = {
        i.incident_id: i
        for i in detect(read, now)
        if i.start_ms >= span_from and not i.from_data_edge
    }
    edge_ids = {i.incident_id for i in detect(read, now) if i.from_data_edge}
    assert {k: v for k, v in whole.items() if k not in edge_ids} == part


def test_thresholds_refuse_what_no_rule_can_use():
    for bad in ({"near_miss_m": 0}, {"stuck_ms": 0}, {"tick_ms": -1}, {"moving_m_s": -0.1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            IncidentThresholds(**bad)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 240), st.booleans())
def test_the_array_near_miss_rule_is_the_plain_one(seed, from_s, some):
    """Over the same tracks, from any tick and for any robots involved: the same runs,
    distances, places and evidence as the rule written plainly (near_miss_reference.py)."""
    tracks = unique_poses(floor_history(seed))
    from_tick = T0 + from_s * 1000
    involving = set(list(tracks)[:1]) if some else None
    assert near_miss_incidents(tracks, TH, from_tick, involving) == reference_near_misses(
        tracks, TH, from_tick, involving
    )
    assert near_miss_incidents(tracks, TH) == reference_near_misses(tracks, TH)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.randoms(use_true_random=False))
def test_pairs_each_from_its_own_tick_in_one_pass_are_each_pair_alone(seed, rng):
    """The live detection's one pass: some pairs each from its own tick (the runs that go
    on), and every other pair with a robot of `involving` from `from_tick`, the robots'
    poses given from the earliest tick each one needs. What the plain rule finds for each
    named pair alone, over its two robots' poses from the newest before its tick, and for
    the others over every robot's poses from the newest before `from_tick`; flags and
    evidence included."""
    tracks = unique_poses(floor_history(seed))
    robots = sorted(tracks)
    pairs = [(a, b) for a in robots for b in robots if a < b]
    from_tick = T0 + rng.randint(0, 480) * TH.tick_ms
    pairs_from = {
        pair: T0 + rng.randint(0, from_tick - T0 + 1) // TH.tick_ms * TH.tick_ms
        for pair in rng.sample(pairs, rng.randint(0, len(pairs)))
    }
    involving = set(rng.sample(robots, rng.randint(0, len(robots))))

    def since(robot: str, ms: int) -> list[PoseRow]:
        track = tracks[robot]
        return track[max(0, bisect.bisect_left(track, ms, key=lambda p: p.ts_ms) - 1) :]

    reach = {
        r: min([from_tick, *(ms for pair, ms in pairs_from.items() if r in pair)]) for r in robots
    }
    together = pose_columns({r: since(r, ms) for r, ms in reach.items()})
    alone = [
        i
        for pair, ms in pairs_from.items()
        for i in reference_near_misses({r: since(r, ms) for r in pair}, TH, ms)
        if i.robots == pair
    ]
    others = [
        i
        for i in reference_near_misses(
            {r: since(r, from_tick) for r in robots}, TH, from_tick, involving
        )
        if i.robots not in pairs_from
    ]
    found = near_misses(together, TH, from_tick, involving, pairs_from)
    assert sorted(found, key=lambda i: i.incident_id) == sorted(
        alone + others, key=lambda i: i.incident_id
    )


@settings(max_examples=300, deadline=None)
@given(
    st.floats(-500, 500).map(lambda v: round(v, 3)),
    st.floats(-500, 500).map(lambda v: round(v, 3)),
    st.floats(0, math.tau),
    st.integers(-3, 3),
    st.sampled_from([0.05, 0.1, 0.25, 1.0]),
)
def test_the_stuck_condition_s_first_part_is_the_distance_to_the_pose_before(
    x, y, heading, off_mm, stuck_m
):
    """Poses a second apart, their distance around the stuck distance (to the millimetre,
    in any direction): the stuck condition can hold at the second exactly when it lies
    nearer than stuck_m to the first, as the rule measures (whole millimetres)."""
    th = IncidentThresholds(stuck_m=stuck_m)
    d = stuck_m + off_mm / 1000
    first = pose(x=x, y=y)
    second = pose(
        t_s=1, x=round(x + d * math.cos(heading), 3), y=round(y + d * math.sin(heading), 3)
    )
    assert stuck_possible_at(first, second, th) == (mm2(first, second) < (stuck_m * 1000) ** 2)
    assert stuck_possible_at(None, second, th)
    assert not stuck_possible_at(first, msgspec.structs.replace(second, path=None), th)
