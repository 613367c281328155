"""Recording conflicts batch by batch against a store, in any arrival order and with repeats,
gives exactly the brute-force answer of the pure rule."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core.conflicts import RecentWrites, all_conflicts
from mapservice.core.ports import ChunkRow
from mapservice.processors.conflict_recorder import (
    UnwrittenConflicts,
    find_conflicts,
    record_conflicts,
    write_conflicts,
)
from mapservice.testing.memory_store import MemoryStore

W = 60_000
H1, H2, H3 = "11" * 16, "22" * 16, "33" * 16


def w(robot: str, ts: int, h: str = H1, row: int = 0, col: int = 0) -> ChunkRow:
    return ChunkRow(row, col, ts, robot, h, ts)


write = st.builds(
    w,
    st.sampled_from(["a", "b", "c", "map-upload"]),
    st.integers(0, 4 * W),
    st.sampled_from([H1, H2, H3]),
    st.integers(0, 1),
    st.just(0),
)


@settings(max_examples=150, deadline=None)
@given(
    writes=st.lists(write, min_size=1, max_size=30),
    cuts=st.lists(st.integers(0, 30), max_size=5),
    repeats=st.lists(st.integers(0, 29), max_size=5),
    window=st.sampled_from([0, W // 2, W]),
    covered_from=st.none() | st.integers(-W, 5 * W),
    forget=st.lists(st.integers(0, 5 * W), max_size=3),
)
def test_batches_in_any_order_with_repeats_equal_the_brute_force(
    writes, cuts, repeats, window, covered_from, forget
) -> None:
    """Store-backed incremental detection (as the sink runs it, with or without the
    in-memory index of recent writes, which may forget old ones) equals all_conflicts."""
    # One identity keeps one content, as a re-delivery carries the same message.
    unique = list({(x.ts_ms, x.row, x.column, x.robot_id): x for x in writes}.values())
    stream = unique + [unique[i % len(unique)] for i in repeats]
    bounds = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
    store = MemoryStore()
    recent = None if covered_from is None else RecentWrites(covered_from)
    for i, (lo, hi) in enumerate(zip(bounds, bounds[1:])):
        batch = stream[lo:hi]
        for x in batch:  # what store.append does for these writes
            store._chunks[(x.ts_ms, x.row, x.column, x.robot_id)] = x
        if recent is not None and i < len(forget):
            recent.forget_before(forget[i])
        record_conflicts(store, batch, window, recent)
    assert store.conflicts(-(10**12), 10**12) == all_conflicts(unique, window)


@settings(max_examples=150, deadline=None)
@given(
    writes=st.lists(write, min_size=1, max_size=30),
    cuts=st.lists(st.integers(0, 30), max_size=5),
    repeats=st.lists(st.integers(0, 29), max_size=5),
    window=st.sampled_from([0, W // 2, W]),
    covered_from=st.none() | st.integers(-W, 5 * W),
    written_after=st.sets(st.integers(0, 6)),
)
def test_conflicts_found_per_batch_and_written_later_equal_the_brute_force(
    writes, cuts, repeats, window, covered_from, written_after
) -> None:
    """find_conflicts per batch, the rows written only after some batches (as the processors
    write them with the pose views) and once at the end, equals all_conflicts, and no
    conflict is stored twice."""
    unique = list({(x.ts_ms, x.row, x.column, x.robot_id): x for x in writes}.values())
    stream = unique + [unique[i % len(unique)] for i in repeats]
    bounds = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
    store = MemoryStore()
    appended: list = []
    original = store.append_conflicts
    store.append_conflicts = lambda rows: (appended.extend(rows), original(rows))[1]
    recent = None if covered_from is None else RecentWrites(covered_from)
    unwritten = UnwrittenConflicts()
    for i, (lo, hi) in enumerate(zip(bounds, bounds[1:])):
        batch = stream[lo:hi]
        for x in batch:
            store._chunks[(x.ts_ms, x.row, x.column, x.robot_id)] = x
        unwritten.add(find_conflicts(store, batch, window, recent))
        if i in written_after:
            write_conflicts(store, unwritten.rows(), recent)
            unwritten.clear()
    write_conflicts(store, unwritten.rows(), recent)
    assert store.conflicts(-(10**12), 10**12) == all_conflicts(unique, window)
    if recent is not None:  # rows it saw written unchanged are never written again
        assert len(appended) == len(set(appended))
