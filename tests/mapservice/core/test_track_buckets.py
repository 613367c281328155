"""The bucket size of the plots' read (core/track_buckets.py): chosen by the span alone, the
smallest round size within the cap, a day whole buckets at every size up to a day."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from mapservice.core.track_buckets import (
    BUCKET_SIZES_MS,
    DAY_MS,
    bucket_size_for,
    buckets_in,
)

WEEK_MS = 7 * DAY_MS


@given(
    from_ms=st.integers(0, 4_000_000_000_000),
    span=st.integers(1, 2 * WEEK_MS),
    cap=st.integers(2, 2000),
)
def test_the_smallest_round_size_within_the_cap(from_ms: int, span: int, cap: int) -> None:
    size = bucket_size_for(from_ms, from_ms + span, cap)
    assert buckets_in(from_ms, from_ms + span, size) <= cap
    smaller = [s for s in BUCKET_SIZES_MS if s < size]
    if size > DAY_MS:
        assert size % DAY_MS == 0
        smaller += list(range(DAY_MS, size, DAY_MS))
    else:
        assert size in BUCKET_SIZES_MS
    assert all(buckets_in(from_ms, from_ms + span, s) > cap for s in smaller)


def test_a_day_is_whole_buckets_at_every_size_up_to_a_day() -> None:
    assert all(DAY_MS % s == 0 for s in BUCKET_SIZES_MS)
    assert list(BUCKET_SIZES_MS) == sorted(BUCKET_SIZES_MS)


@given(st.integers(0, 10**13), st.integers(0, 10**7), st.sampled_from(BUCKET_SIZES_MS))
def test_buckets_in_counts_the_buckets_a_window_meets(from_ms: int, span: int, size: int) -> None:
    met = {t // size for t in range(from_ms, from_ms + span, max(1, size // 4))}
    met |= {(from_ms + span - 1) // size} if span else set()
    assert buckets_in(from_ms, from_ms + span, size) == len(met)
