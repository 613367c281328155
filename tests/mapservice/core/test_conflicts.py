"""The conflict rule, as pure functions: who conflicts with whom, the neighbourhoods a new
batch must be compared with, the in-memory index of recent writes."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.core.conflicts import (
    RecentWrites,
    affected_conflicts,
    all_conflicts,
    conflicts_of,
    neighbourhoods,
)
from mapservice.core.ports import ChunkRow, ConflictRow

W = 60_000
H1, H2, H3 = "11" * 16, "22" * 16, "33" * 16


def w(robot: str, ts: int, h: str = H1, row: int = 0, col: int = 0) -> ChunkRow:
    return ChunkRow(row, col, ts, robot, h, ts)


def test_different_robots_different_content_within_window_conflict() -> None:
    """a then b with different content within the window is one conflict at b's time."""
    a, b = w("a", 1000, H1), w("b", 5000, H2)
    assert all_conflicts([a, b], W) == [ConflictRow(0, 0, 5000, "a", 1000, "b")]


def test_no_conflict_for_same_content_same_robot_other_chunk_or_outside_window() -> None:
    """Same content, the same robot, another chunk, or further apart than the window: none."""
    assert all_conflicts([w("a", 0, H1), w("b", 10, H1)], W) == []
    assert all_conflicts([w("a", 0, H1), w("a", 10, H2)], W) == []
    assert all_conflicts([w("a", 0, H1), w("b", 10, H2, row=1)], W) == []
    assert all_conflicts([w("a", 0, H1), w("b", W + 1, H2)], W) == []
    assert len(all_conflicts([w("a", 0, H1), w("b", W, H2)], W)) == 1  # the window is closed


def test_equal_times_are_ordered_by_robot() -> None:
    """Two robots at one instant: the conflict's B is the greater robot id, once."""
    assert all_conflicts([w("b", 7, H2), w("a", 7, H1)], W) == [ConflictRow(0, 0, 7, "a", 7, "b")]


def test_one_conflict_per_b_naming_the_latest_conflicting_a() -> None:
    """Several conflicting writes before B, of several robots: one conflict, naming the
    latest of them (a write with B's own content does not conflict)."""
    rows = conflicts_of(
        w("b", 100, H3), [w("a", 10, H1), w("a", 50, H2), w("a", 90, H3), w("c", 20, H1)], W
    )
    assert rows == [ConflictRow(0, 0, 100, "a", 50, "b")]


def test_ties_in_time_pick_the_greater_robot_as_a() -> None:
    """Two conflicting writes at one instant before B: A is the greater robot id."""
    rows = conflicts_of(w("d", 100, H3), [w("c", 40, H1), w("a", 40, H2)], W)
    assert rows == [ConflictRow(0, 0, 100, "c", 40, "d")]


def test_late_write_as_a_creates_conflicts_with_later_writes() -> None:
    """A late write is checked as A against stored later writes of other robots (whose
    conflicts are all recomputed: c's existing conflict with b comes back unchanged)."""
    stored = [w("b", 5000, H2), w("c", 9000, H1)]
    late = w("a", 1000, H1)
    got = affected_conflicts([late], stored + [late], W)
    assert [(c.robot_a, c.robot_b, c.ts_ms) for c in got] == [("a", "b", 5000), ("b", "c", 9000)]


def test_late_write_moves_a_conflicts_a_to_itself_when_later() -> None:
    """A late write between B's current A and B becomes B's A (and has its own conflict)."""
    stored = [w("a", 1000, H1), w("b", 5000, H2)]
    late = w("c", 3000, H3)
    assert affected_conflicts([late], stored + [late], W) == [
        ConflictRow(0, 0, 3000, "a", 1000, "c"),
        ConflictRow(0, 0, 5000, "c", 3000, "b"),
    ]


def test_neighbourhoods_cover_the_window_and_split_distant_writes() -> None:
    """Writes far apart in time are read separately, each range widened by the window."""
    got = neighbourhoods([w("a", 0, row=1), w("b", 100, col=2), w("a", 10 * W)], W)
    assert got == [([(0, 2), (1, 0)], -W, 100 + W), ([(0, 0)], 9 * W, 11 * W)]


def test_recent_writes_cover_only_from_their_start() -> None:
    """The index answers for windows from its start on, and forgets what is older."""
    recent = RecentWrites(1000, [w("a", 500), w("a", 1000), w("b", 2000, row=1)])
    assert not recent.covers(999) and recent.covers(1000)
    assert [x.ts_ms for x in recent.near([(0, 0), (1, 0)], 0, 5000)] == [1000, 2000]
    recent.forget_before(1500)
    assert len(recent) == 1 and not recent.covers(1499)


_write = st.builds(
    w,
    st.sampled_from(["a", "b", "c"]),
    st.integers(0, 3 * W),
    st.sampled_from([H1, H2, H3]),
    st.integers(0, 1),
)


@settings(max_examples=200, deadline=None)
@given(
    old=st.lists(_write, max_size=40),
    new=st.lists(_write, min_size=1, max_size=10),
    window=st.sampled_from([0, W // 2, W]),
)
def test_the_sorted_index_finds_what_the_pure_rule_finds(old, new, window) -> None:
    """RecentWrites.affected (its chunks kept sorted, repeats kept once) equals
    affected_conflicts over the same writes, repeats and all."""
    recent = RecentWrites(0, old + new[:1])
    recent.add(new)
    assert recent.affected(new, window) == affected_conflicts(new, old + new[:1] + new, window)


def test_a_map_upload_is_never_a_conflict() -> None:
    """The map uploader's writes (the start-up upload against the simulator) are neither A
    nor B; the robots' writes around it still conflict among themselves, skipping it."""
    from mapservice.core.conflicts import UPLOADER_ID

    sim = w("sim-001", 1000, H1)
    upload = w(UPLOADER_ID, 2000, H2)
    after = w("sim-002", 3000, H3)
    assert conflicts_of(upload, [sim], W) == []
    assert conflicts_of(w("sim-001", 4000, H1), [upload], W) == []
    # sim-002's write conflicts with sim-001's, not with the later upload between them.
    assert all_conflicts([sim, upload, after], W) == [
        ConflictRow(0, 0, 3000, "sim-001", 1000, "sim-002")
    ]
    assert affected_conflicts([upload], [sim, upload, after], W) == [
        ConflictRow(0, 0, 3000, "sim-001", 1000, "sim-002")
    ]
    index = RecentWrites(0, [sim, upload])
    assert index.affected([upload], W) == []
