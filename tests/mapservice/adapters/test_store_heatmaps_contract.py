"""The store contract, the heatmaps' read (`HeatmapReader.heatmap_cells`): a span's cells
by core/heatmaps.py's rule, whether ClickHouse reads them from its pre-aggregated buckets
(heatmap_cells, written by the snapshot builds) or from the poses.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py. The constructed tests check exact cell values just inside and
outside the thresholds; the generated one compares the store with a plain fold of its own
raw poses on random histories, with snapshots built at a random instant (so a span is read
partly from the buckets, partly from the poses), and ClickHouse's buckets alone once the
poses are gone.
"""

from __future__ import annotations

import itertools

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.heatmaps import BUCKET_MS, HeatmapCell, HeatmapRule, fold_heatmap

_robots = itertools.count()
_examples = itertools.count()


def _constructed(ev, s: int) -> list:
    return [
        # a: the pose 5 s before the span makes the first sample's speed known (0: still);
        # the pose at 1.5 s is no sample (the second's first pose is); 0.5 m in a second
        # (moving), then still, then a 20 s silence: its speed is unknown.
        ev.pose("a", s - 5_000, x=0.1, y=0.1),
        ev.pose("a", s, x=0.1, y=0.1),
        ev.pose("a", s + 1_000, x=0.1, y=0.1),
        ev.pose("a", s + 1_500, x=5.0, y=5.0),
        ev.pose("a", s + 2_000, x=0.6, y=0.1),
        ev.pose("a", s + 3_000, x=0.6, y=0.1),
        ev.pose("a", s + 23_000, x=0.6, y=0.1),
        # b: one sample at a negative x (cells floor: -0.2 m is cell -1).
        ev.pose("b", s + 500, x=-0.2, y=0.7),
        # c: 49 mm in a second is still (below 0.05 m/s), 50 mm is not.
        ev.pose("c", s, x=10.0, y=10.0),
        ev.pose("c", s + 1_000, x=10.049, y=10.0),
        ev.pose("c", s + 2_000, x=10.099, y=10.0),
        # d: a silence of exactly the offline threshold keeps the speed, 1 ms more loses it.
        ev.pose("d", s, x=20.0, y=20.0),
        ev.pose("d", s + 10_000, x=20.0, y=20.0),
        ev.pose("d", s + 20_001, x=20.0, y=20.0),
    ]


def _by_cell(cells: list[HeatmapCell]) -> dict[tuple[int, int], tuple]:
    return {(c.i, c.j): (c.samples, c.still, c.speeds, round(c.speed_sum, 9)) for c in cells}


FINEST = {
    (0, 0): (2, 2, 2, 0.0),
    (1, 0): (3, 1, 2, 0.5),
    (-1, 1): (1, 0, 0, 0.0),
    (20, 20): (3, 1, 2, 0.099),
    (40, 40): (3, 1, 1, 0.0),
}
# The same with a's pose before the span in it: one more sample, of unknown speed.
FINEST_WITH_LEAD = {**FINEST, (0, 0): (3, 2, 2, 0.0)}


def test_cells_of_constructed_poses(store, ev, t0) -> None:
    s = t0 - t0 % BUCKET_MS + BUCKET_MS // 2  # inside one bucket
    store.append(_constructed(ev, s))
    store.append(_constructed(ev, s)[3:6])  # a redelivered batch counts once
    assert _by_cell(store.heatmap_cells(s, s + 60_000, 1)) == FINEST
    # 1 m cells: the finest cells (0, 0) and (1, 0) are cell (0, 0); (-1, 1) is (-1, 0).
    assert _by_cell(store.heatmap_cells(s, s + 60_000, 2)) == {
        (0, 0): (5, 3, 4, 0.5),
        (-1, 0): (1, 0, 0, 0.0),
        (10, 10): (3, 1, 2, 0.099),
        (20, 20): (3, 1, 1, 0.0),
    }
    # A span's samples are those whose second starts in it; the previous ones still count
    # for their speed.
    assert _by_cell(store.heatmap_cells(s + 2_000, s + 3_000, 1)) == {
        (1, 0): (1, 0, 1, 0.5),
        (20, 20): (1, 0, 1, 0.05),
    }
    assert _by_cell(store.heatmap_cells(s + 2_001, s + 3_000, 1)) == {}
    assert (
        store.heatmap_cells(s, s + 60_000, 1, limit=2) == store.heatmap_cells(s, s + 60_000, 1)[:2]
    )
    with pytest.raises(ValueError):
        store.heatmap_cells(s, s + 60_000, 0)


def test_cells_across_built_buckets_equal_the_cells_before(store, ev, t0) -> None:
    """Snapshots built after the history: ClickHouse then reads whole buckets from
    heatmap_cells, and the same cells come back, also across a bucket edge."""
    s = t0 - t0 % BUCKET_MS - 2 * BUCKET_MS - 2_000  # 2 s before a bucket edge
    store.append(_constructed(ev, s))
    spans = [(s, s + 60_000), (s - BUCKET_MS, s + 2 * BUCKET_MS), (s + 2_000, s + 3 * BUCKET_MS)]
    before = [store.heatmap_cells(f, t, k) for f, t in spans for k in (1, 3)]
    store.build_snapshots(s + 3 * BUCKET_MS)
    assert [store.heatmap_cells(f, t, k) for f, t in spans for k in (1, 3)] == before
    assert _by_cell(store.heatmap_cells(s - BUCKET_MS, s + 2 * BUCKET_MS, 1)) == FINEST_WITH_LEAD


# Tracks: a start and (gap from the pose before in ms, x, y, step) per pose: mostly a
# second apart, some faster or a little slower, now and then a silence over the offline
# threshold; positions on a small floor so cells repeat, many a few centimetres from the
# pose before (standing, creeping: dwell; step 0 is a jump). Some poses sent again, several
# robots, stored in shuffled batches.
_pose = st.tuples(
    st.sampled_from([1000, 1000, 1000, 400, 1500, 10_000, 10_001, 45_000]),
    st.integers(-3000, 3000).map(lambda mm: mm / 1000),
    st.integers(-3000, 3000).map(lambda mm: mm / 1000),
    st.sampled_from([0, 1, 1, 30, 49, 50, 80]),  # mm along x from the pose before (0: jump)
)
_track = st.tuples(st.integers(0, 2 * BUCKET_MS), st.lists(_pose, min_size=20, max_size=80))


@settings(
    max_examples=20,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    tracks=st.lists(_track, min_size=1, max_size=3),
    resent=st.lists(st.integers(0, 39), max_size=10),
    batches=st.integers(1, 3),
    built=st.one_of(st.integers(0, 4 * BUCKET_MS), st.just(4 * BUCKET_MS)),
    cut=st.tuples(st.integers(0, BUCKET_MS), st.integers(0, BUCKET_MS)),
    factor=st.sampled_from([1, 2, 5]),
    order=st.randoms(use_true_random=False),
)
def test_cells_equal_a_plain_fold_of_the_raw_poses(
    store, ev, t0, tracks, resent, batches, built, cut, factor, order
) -> None:
    # Each example later than the one before, 6 buckets apart: its snapshots are built
    # after the earlier examples' and before its own poses are late.
    base = t0 - t0 % BUCKET_MS - 100 * 3_600_000 + next(_examples) * 6 * BUCKET_MS
    robots = [f"h{next(_robots)}" for _ in tracks]
    events = []
    for robot, (t, track) in zip(robots, tracks, strict=True):
        at = None
        for gap, x, y, step in track:
            t += gap
            at = (x, y) if at is None or not step else (round(at[0] + step / 1000, 3), at[1])
            events.append(ev.pose(robot, base + t, x=at[0], y=at[1]))
    events += [events[i] for i in resent if i < len(events)]
    order.shuffle(events)
    for k in range(min(batches, len(events))):
        store.append(events[k::batches])
    f, t = base + cut[0], base + 4 * BUCKET_MS - cut[1]
    raw = store.poses(base - 60_000, base + 5 * BUCKET_MS, None)
    want = fold_heatmap(raw, f, t, factor, HeatmapRule())
    store.build_snapshots(base + built)
    got = store.heatmap_cells(f, t, factor)
    assert [(c.i, c.j, c.samples, c.still, c.speeds) for c in got] == [
        (c.i, c.j, c.samples, c.still, c.speeds) for c in want
    ]
    for g, w in zip(got, want, strict=True):
        assert g.speed_sum == pytest.approx(w.speed_sum, rel=1e-9, abs=1e-12)


def test_clickhouse_reads_whole_buckets_from_its_pre_aggregation(store, ev, t0) -> None:
    """Once the snapshots are built, the buckets alone answer: with the poses gone, a span
    of whole buckets before the newest snapshot has the same cells (the memory store folds
    its poses and has none to lose)."""
    if not hasattr(store, "connection"):
        pytest.skip("the memory store keeps no pre-aggregation")
    s = t0 - t0 % BUCKET_MS - 3 * BUCKET_MS
    store.append(_constructed(ev, s + 10_000))
    span = (s, s + 2 * BUCKET_MS)
    before = store.heatmap_cells(*span, 1)
    assert _by_cell(before) == FINEST_WITH_LEAD
    store.build_snapshots(s + 3 * BUCKET_MS)
    for table in ("poses", "pose_tracks"):
        store.connection.client.command(f"TRUNCATE TABLE {store.database}.{table}")
    assert store.heatmap_cells(*span, 1) == before
    # A partial bucket is read from the poses: now empty.
    assert store.heatmap_cells(s + 1, s + 2 * BUCKET_MS, 1) == []
