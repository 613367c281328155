"""The store contract, the plots' read (`TimeTravelReader.track_buckets`): one robot's
poses aggregated per absolute bucket from every pose, by core/track_buckets.py's rule.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py. The generated tests fold the store's own raw poses
(`poses`, another table in ClickHouse) plainly and compare: each bucket's figures at
several sizes, and the buckets' distances adding up to the window's at every size, on
random tracks with re-sent poses, silent gaps and batches stored out of order.
"""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.track_buckets import BUCKET_SIZES_MS

_robots = itertools.count()


def test_a_step_counts_once_in_the_bucket_of_its_later_pose(store, ev, t0) -> None:
    """Steps of 3-4-5 triangles across a bucket edge: each counts where it ends; the
    window's first pose starts none; speed is distance over the steps' time; battery min,
    max and mean over the poses reporting one; a re-sent pose counts once."""
    b = 10_000
    start = t0 - t0 % b
    store.append(
        [
            ev.pose("r", start + 9_000, x=3.0, y=4.0, battery_level=50.0),
            ev.pose("r", start + 1_000, x=0.0, y=0.0, battery_level=60.0),
            ev.pose("r", start + 12_000, x=3.0, y=0.0, battery_level=None),
            ev.pose("r", start + 19_000, x=0.0, y=0.0, battery_level=40.0),
            ev.pose("r", start + 15_000, x=3.0, y=4.0, battery_level=45.0),
            ev.pose("other", start + 5_000, x=100.0),
        ]
    )
    # A batch delivered again: its poses stored once.
    store.append([ev.pose("r", start + 15_000, x=3.0, y=4.0, battery_level=45.0)])
    got = store.track_buckets("r", start, start + 2 * b, b)
    assert [
        (k.start_ms - start, k.poses, k.steps, k.first_ms - start, k.last_ms - start) for k in got
    ] == [(0, 2, 1, 1_000, 9_000), (b, 3, 3, 12_000, 19_000)]
    assert got[0].distance_m == pytest.approx(5.0) and got[0].step_ms == 8_000
    # 9 s -> 12 s: 4 m; 12 s -> 15 s: 4 m; 15 s -> 19 s: 5 m.
    assert got[1].distance_m == pytest.approx(13.0) and got[1].step_ms == 10_000
    assert (got[0].battery_min, got[0].battery_max, got[0].battery_mean) == (50.0, 60.0, 55.0)
    assert (got[1].battery_min, got[1].battery_max) == (40.0, 45.0)
    assert got[1].battery_mean == pytest.approx(42.5)
    # A window starting after the first pose: its first pose starts no step.
    later = store.track_buckets("r", start + 9_000, start + 2 * b, b)
    assert [k.steps for k in later] == [0, 3] and later[0].distance_m == 0.0
    assert store.track_buckets("nobody", start, start + 2 * b, b) == []
    with pytest.raises(ValueError):
        store.track_buckets("r", start, start + b, 0)


def _plain_fold(poses, bucket_ms):
    """Per bucket start: [poses, steps, distance, step time, battery levels], from the
    raw poses in time order, each step credited to the bucket of its later pose."""
    out: dict[int, list] = {}
    for i, p in enumerate(poses):
        cell = out.setdefault(p.ts_ms // bucket_ms * bucket_ms, [0, 0, 0.0, 0, []])
        cell[0] += 1
        if p.battery_level is not None:
            cell[4].append(p.battery_level)
        if i:
            q = poses[i - 1]
            cell[1] += 1
            cell[2] += math.dist((q.x, q.y), (p.x, p.y))
            cell[3] += p.ts_ms - q.ts_ms
    return out


# A track: (offset in ms, x, y, battery or None) per pose, one per offset; some sent again
# (a redelivered batch), a silent gap in the middle; stored in shuffled batches.
_pose = st.tuples(
    st.one_of(st.integers(0, 120_000), st.integers(0, 40).map(lambda k: k * 3_000)),
    st.floats(-500, 500, allow_nan=False),
    st.floats(-500, 500, allow_nan=False),
    st.one_of(st.none(), st.floats(0, 100, allow_nan=False, width=32)),
)


@settings(
    max_examples=12,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    track=st.lists(_pose, min_size=1, max_size=60, unique_by=lambda p: p[0]),
    resent=st.lists(st.integers(0, 59), max_size=20),
    batches=st.integers(1, 4),
    gap=st.integers(0, 3_000_000),
    cut=st.tuples(st.integers(0, 30_000), st.integers(0, 30_000)),
    order=st.randoms(use_true_random=False),
)
def test_buckets_equal_a_plain_fold_of_the_raw_poses_at_every_size(
    store, ev, t0, track, resent, batches, gap, cut, order
) -> None:
    robot = f"g{next(_robots)}"
    # A silent gap: the second half of the track after `gap` ms without a pose.
    # One pose per instant (a second pose at an instant is a rewrite, not a redelivery).
    at = {
        t + (gap if i >= len(track) // 2 else 0): (x, y, b) for i, (t, x, y, b) in enumerate(track)
    }
    events = [ev.pose(robot, t0 + t, x=x, y=y, battery_level=b) for t, (x, y, b) in at.items()]
    events += [events[i] for i in resent if i < len(events)]
    order.shuffle(events)
    for k in range(min(batches, len(events))):
        store.append(events[k::batches])
    first = t0 + cut[0]
    last = t0 + 120_001 + gap - cut[1]
    raw = store.poses(first, last, robot)
    total = sum(math.dist((q.x, q.y), (p.x, p.y)) for q, p in itertools.pairwise(raw))
    for bucket_ms in (1_000, 7_000, 60_000, 3_600_000, *BUCKET_SIZES_MS[-1:]):
        got = store.track_buckets(robot, first, last, bucket_ms)
        want = _plain_fold(raw, bucket_ms)
        assert [b.start_ms for b in got] == sorted(want), bucket_ms
        for b in got:
            poses, steps, distance, step_ms, levels = want[b.start_ms]
            assert (b.poses, b.steps, b.step_ms) == (poses, steps, step_ms)
            assert b.distance_m == pytest.approx(distance, rel=1e-9, abs=1e-9)
            assert b.battery_min == (min(levels) if levels else None)
            assert b.battery_max == (max(levels) if levels else None)
            if levels:
                assert b.battery_mean == pytest.approx(sum(levels) / len(levels), rel=1e-6)
            else:
                assert b.battery_mean is None
        # Every bucketing of the window adds up to the window's distance and step time.
        assert sum(b.distance_m for b in got) == pytest.approx(total, rel=1e-9, abs=1e-9)
        assert sum(b.step_ms for b in got) == (raw[-1].ts_ms - raw[0].ts_ms if raw else 0)
        assert sum(b.poses for b in got) == len(raw)
