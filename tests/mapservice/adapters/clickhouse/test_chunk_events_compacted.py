"""chunk_events_compacted: one contract for MemoryStore and ClickHouseStore (embedded chDB).

Per chunk and absolute bucket [k*step, (k+1)*step) of the window, only the bucket's winning
write (greatest (event time, robot id), map_at's rule), ordered like chunk_events(); checked
against a naive fold of the raw events, with duplicates and late events.
"""

from __future__ import annotations

import random
import time

import pytest

from mapservice.core.timetravel import fold_map

MIN = 60_000


@pytest.fixture
def t0() -> int:
    """A whole ten minutes about an hour ago (inside the retention)."""
    return (time.time_ns() // 1_000_000 // 600_000) * 600_000 - 3_600_000


def _key(rows, t0):
    return [(r.row, r.column, r.ts_ms - t0, r.robot_id) for r in rows]


def test_each_chunk_keeps_its_last_write_per_absolute_bucket(store, ev, t0) -> None:
    """Per chunk and minute the latest write survives; a tie in time goes to the greater robot id."""
    store.append(
        [
            ev.chunk("a", t0 + 1_000, 0, 0),
            ev.chunk("a", t0 + 50_000, 0, 0),
            ev.chunk("b", t0 + 50_000, 0, 0, bytes([1]) * 10_000),
            ev.chunk("a", t0 + 20_000, 0, 1),
            ev.chunk("a", t0 + 61_000, 0, 0),
            ev.chunk("a", t0 + 119_999, 0, 0),
        ]
    )
    rows = store.chunk_events_compacted(t0, t0 + 3 * MIN, MIN)
    assert _key(rows, t0) == [(0, 1, 20_000, "a"), (0, 0, 50_000, "b"), (0, 0, 119_999, "a")]
    assert rows[1].content_hash == store.chunk_events(t0 + 50_000, t0 + 50_001)[1].content_hash


def test_window_ends_cut_the_buckets_they_fall_in(store, ev, t0) -> None:
    """A window starting or ending inside a bucket returns the winner of the part inside it."""
    store.append([ev.chunk("a", t0 + o, 0, 0) for o in (10_000, 30_000, 70_000, 100_000)])
    assert _key(store.chunk_events_compacted(t0 + 20_000, t0 + 90_000, MIN), t0) == [
        (0, 0, 30_000, "a"),
        (0, 0, 70_000, "a"),
    ]


def test_limit_keeps_the_earliest_and_step_must_be_positive(store, ev, t0) -> None:
    """The limit cuts the time-ordered answer; a step of 0 or less is refused."""
    store.append([ev.chunk("a", t0 + k * MIN, k % 3, 0) for k in range(6)])
    assert [
        r.ts_ms - t0 for r in store.chunk_events_compacted(t0, t0 + 10 * MIN, MIN, limit=2)
    ] == [0, MIN]
    with pytest.raises(ValueError):
        store.chunk_events_compacted(t0, t0 + MIN, 0)


def _naive(events, f: int, t: int, step: int) -> list[tuple]:
    """The compaction by hand: per (row, column, ts // step) the max (ts, robot) write."""
    won: dict[tuple, tuple] = {}
    for e in events:
        if f <= e[0] < t:
            k = (e[2], e[3], e[0] // step)
            if k not in won or e[:2] > won[k][:2]:
                won[k] = e
    return sorted(
        ((e[2], e[3], e[0], e[1]) for e in won.values()), key=lambda x: (x[2], x[0], x[1], x[3])
    )


def test_compacted_writes_equal_a_naive_fold_and_give_the_exact_map_at_every_boundary(
    store, ev, t0
) -> None:
    """Random writes, re-delivered duplicates and late arrivals: the answer equals a naive
    compaction, and folding it onto the map before the window gives map_at at each bucket
    boundary and at the window's end."""
    rng = random.Random(5)
    events = sorted(
        {
            (
                t0 + rng.randrange(0, 30 * MIN, 250),
                rng.choice("abc"),
                rng.randrange(3),
                rng.randrange(3),
            )
            for _ in range(400)
        }
    )
    pixels = {e: bytes([rng.randrange(256)]) * 100 for e in events}
    env = {e: ev.chunk(e[1], e[0], e[2], e[3], pixels[e], width=10, height=10) for e in events}
    on_time = [e for e in events if e[0] % 7]
    store.append([env[e] for e in on_time])
    store.append([env[e] for e in on_time[::5]])  # re-delivered
    store.append([env[e] for e in events if not e[0] % 7])  # late: older than what is stored
    step = 5 * MIN
    f, t = t0 + 2 * MIN + 123, t0 + 27 * MIN + 7
    rows = store.chunk_events_compacted(f, t, step)
    assert [(r.row, r.column, r.ts_ms, r.robot_id) for r in rows] == _naive(events, f, t, step)
    base = store.map_at(f - 1)
    for b in [*range((f // step + 1) * step, t, step), t]:
        folded = fold_map([*base, *(r for r in rows if r.ts_ms < b)], b - 1)
        assert folded == fold_map(store.map_at(b - 1), b - 1), b - t0
