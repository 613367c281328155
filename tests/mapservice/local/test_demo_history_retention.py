"""The demo's floor is written once, at the history's first instant. Merges (which apply
whatever TTL a table has, as days of running do) and the retention step must leave it
whole: at the first instant, and at the retention boundary once the days before are gone."""

from __future__ import annotations

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import load_ros_map, slice_chunks
from mapservice.local.demo_history import backfill
from tests.fixtures.paths import MAPS

DAY = 86_400_000
# Ten days before a fixed instant that is itself in the past: older than any real-clock TTL.
END = 1_795_255_200_000 - 10 * DAY


def test_an_old_demo_keeps_its_floor_through_merges_and_the_retention(tmp_path) -> None:
    store = ClickHouseStore(f"chdb://{tmp_path / 'ch'}", "mapservice", 7, snapshot_every_ms=600_000)
    store.migrate()
    ros_map = load_ros_map(MAPS / "depot.yaml")
    result = backfill(
        store, ros_map, days=0.05, robots=2, now_ms=END, conflict_window_ms=60_000, seed=3
    )
    store.optimize()
    floor = set(slice_chunks(ros_map))

    def whole_at(t: int) -> None:
        chunks = store.map_at(t)
        assert {(c.row, c.column) for c in chunks} == floor, (
            f"{len(chunks)} of {len(floor)} chunks at {(END - t) / 3_600_000:.1f} h before the end"
        )
        named = {bytes.fromhex(c.content_hash) for c in chunks}
        assert set(store.chunk_contents(list(named))) == named, "pixels missing"

    whole_at(result.start_ms + 1000)
    whole_at(END)
    # Eight days later the demo's day lies before the retention: only the floor it built stays.
    later = END + 8 * DAY
    # The snapshot timer's eight days, built as the demo builds its own (build_snapshots'
    # rows in a few statements instead of five per each of 1,152 snapshots).
    store.build_snapshots_bulk(later)
    done = store.apply_retention(later)
    assert done.partitions_dropped > 0
    assert not store.chunk_events(0, later)
    store.optimize()
    whole_at(later - 7 * DAY)
    whole_at(later)
    assert len(store.robots_at(later)) == 2  # the robots' last poses, carried
    store.close()
