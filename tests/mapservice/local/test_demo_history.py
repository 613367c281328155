"""The demo history: the shift simulator fast-forwarded into a real chDB store, checked against
brute force (map and robots at T, conflicts) and the map (robots on free pixels)."""

from __future__ import annotations

import random
import zlib

import numpy as np
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import drivable, load_ros_map, slice_chunks
from mapservice.core.conflicts import all_conflicts, conflict_key
from mapservice.core.wire2019 import content_hash
from mapservice.local.demo_history import UPLOAD_ROBOT_ID, backfill
from mapservice.robot.chunks import metres_to_pixel
from tests.fixtures.paths import MAPS

NOW = 1_795_255_200_000
HOURS = 3
WINDOW_MS = 60_000


@pytest.fixture(scope="module")
def history(tmp_path_factory):
    """Three hours of three robots on the depot, stored as the processors would."""
    store = ClickHouseStore(
        f"chdb://{tmp_path_factory.mktemp('demo')}", "mapservice", 7, snapshot_every_ms=600_000
    )
    store.migrate()
    ros_map = load_ros_map(MAPS / "depot.yaml")
    result = backfill(
        store, ros_map, days=HOURS / 24, robots=3, now_ms=NOW, conflict_window_ms=WINDOW_MS, seed=5
    )
    yield store, ros_map, result
    store.close()


def stitched(store, ros_map, at_ms: int) -> np.ndarray:
    """The map at `at_ms` as pixels, from the store's own chunks."""
    meta = store.latest_meta()
    canvas = np.zeros(
        (meta.chunk_rows * meta.chunk_height, meta.chunk_cols * meta.chunk_width), np.uint8
    )
    for c in store.map_at(at_ms):
        w, h, data = store.chunk_content(bytes.fromhex(c.content_hash))
        canvas[c.row * h : (c.row + 1) * h, c.column * w : (c.column + 1) * w] = np.frombuffer(
            zlib.decompress(data), np.uint8
        ).reshape(h, w)
    return canvas[: ros_map.height, : ros_map.width]


def test_history_starts_with_the_map_file(history) -> None:
    """At the first instant the map is the map file, every chunk written by the upload."""
    store, ros_map, result = history
    at_start = {(c.row, c.column): c for c in store.map_at(result.start_ms)}
    expected = slice_chunks(ros_map)
    assert set(at_start) == set(expected)
    assert all(c.robot_id == UPLOAD_ROBOT_ID for c in at_start.values())
    assert all(at_start[k].content_hash == content_hash(px).hex() for k, px in expected.items())


def test_it_holds_a_shift_poses_changes_and_conflicts(history) -> None:
    """Three robots report every 3 s for three hours; the floor changed; conflicts were recorded."""
    _store, _, result = history
    assert result.poses == pytest.approx(3 * HOURS * 3600 / 3, rel=0.01)
    assert result.chunk_writes > 0 and result.snapshots >= HOURS * 6
    assert result.conflicts > 0


def test_map_and_robots_at_t_equal_the_fold_of_the_history(history) -> None:
    """At random instants, map at T and robots at T (snapshots plus events) equal brute force."""
    store, _, result = history
    writes = store.chunk_events(0, NOW + 1, limit=1_000_000)
    poses = store.poses(result.start_ms, NOW + 1, limit=1_000_000)
    rng = random.Random(1)
    for at in [result.start_ms + rng.randrange(NOW - result.start_ms) for _ in range(8)]:
        fold: dict = {}
        for w in writes:
            if (w.ts_ms <= at and (w.row, w.column) not in fold) or (
                w.ts_ms <= at
                and (w.ts_ms, w.robot_id)
                > (fold[(w.row, w.column)].ts_ms, fold[(w.row, w.column)].robot_id)
            ):
                fold[(w.row, w.column)] = w
        got = {(c.row, c.column): (c.ts_ms, c.robot_id, c.content_hash) for c in store.map_at(at)}
        assert got == {k: (w.ts_ms, w.robot_id, w.content_hash) for k, w in fold.items()}
        latest: dict = {}
        for p in poses:
            if p.ts_ms <= at:
                latest[p.robot_id] = p
        assert {(p.robot_id, p.ts_ms) for p in store.robots_at(at)} == {
            (p.robot_id, p.ts_ms) for p in latest.values()
        }
        # Every robot reported within the offline threshold (10 s) of T: drawn online.
        assert all(at - p.ts_ms <= 10_000 for p in latest.values() if at - result.start_ms > 10_000)


def test_conflicts_equal_brute_force(history) -> None:
    """The recorded conflicts are exactly those a fold of every chunk write gives."""
    store, _, _ = history
    writes = store.chunk_events(0, NOW + 1, limit=1_000_000)
    expected = all_conflicts(writes, WINDOW_MS)
    got = sorted(store.conflicts(0, NOW + 1), key=conflict_key)
    assert [conflict_key(c) for c in got] == [conflict_key(c) for c in expected]
    assert {(c.robot_a, c.ts_a_ms) for c in got} == {(c.robot_a, c.ts_a_ms) for c in expected}


def test_every_robot_stands_on_a_free_pixel_of_the_map_at_its_time(history) -> None:
    """Sampled poses lie on drivable pixels of the map as it was at their instant (pallets included)."""
    store, ros_map, result = history
    meta = store.latest_meta()
    rng = random.Random(2)
    for at in [
        result.start_ms + 60_000 + rng.randrange(NOW - result.start_ms - 60_000) for _ in range(6)
    ]:
        free = drivable(ros_map.with_pixels(stitched(store, ros_map, at)))
        for p in store.robots_at(at):
            col, row = metres_to_pixel(p.x, p.y, meta)
            assert free[row, col], f"{p.robot_id} on a blocked pixel at {p.x}, {p.y} ({at})"


def test_the_pose_views_hold_every_robot_the_poses_hold(history) -> None:
    """The demo derives the pose views from the stored rows (derive_views_between): the
    timeline's robots per bucket and the downsampled replay match the poses themselves."""
    store, _, result = history
    buckets = store.timeline(result.start_ms, result.end_ms, 18)
    poses = store.poses(result.start_ms, result.end_ms, limit=10_000_000)
    span = buckets[1].start_ms - buckets[0].start_ms
    want = [set() for _ in buckets]
    for p in poses:
        want[(p.ts_ms - result.start_ms) // span].add(p.robot_id)
    assert [b.robots_active for b in buckets] == [len(w) for w in want]
    minute = 60_000
    lo = -(-result.start_ms // minute) * minute
    frames = store.poses_downsampled(lo, lo + 30 * minute, minute)
    firsts = {}
    for p in store.poses(lo, lo + 30 * minute, limit=10_000_000):
        firsts.setdefault((p.robot_id, (p.ts_ms - lo) // minute), p.ts_ms)
    assert sorted((p.robot_id, p.ts_ms) for p in frames) == sorted(
        (r, t) for (r, _), t in firsts.items()
    )
