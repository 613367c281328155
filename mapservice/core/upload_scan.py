"""A span's map uploads, found where one writer's writes bunch up, not by reading every
write of the span (pure: the stores pass their two reads in).

The change feed classifies a span's writes by reading them all (core/change_scan.py), and
refuses a span holding more than `change_feed.MAX_WRITES`: a day or a week of a large
fleet. The timeline asks for the uploads alone, and they are rare and dense: an upload's
first UPLOAD_MIN_CHUNKS writes lie within (UPLOAD_MIN_CHUNKS - 1) * UPLOAD_GAP_MS <
BURST_BUCKET_MS, so they fall into at most two buckets of BURST_BUCKET_MS (aligned to the
epoch) and one of the two holds at least BURST_MIN_WRITES of that writer's writes. The store
answers which (writer, bucket) pairs hold that many (and every bucket the map uploader
wrote in: its writes are an upload however few) with one aggregate that hands no write
out. Only those writers' writes around those buckets are then read, and
`change_feed.page` classifies them as it would every write of the span: a run is one
writer's, so its other writers' writes change nothing about it.

A run whose extent covers a whole bucket holds at least BURST_MIN_WRITES writes in it
(writes at most UPLOAD_GAP_MS apart across BURST_BUCKET_MS), so every bucket inside an
upload is found and the margin around the found ones reaches the upload's ends; a run
still going on at the edge of what was read is followed (that writer's writes only) until
it ends, so its size and last write are whole.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

from mapservice.core import change_feed
from mapservice.core.change_feed import (
    MARGIN_MS,
    UPLOAD_GAP_MS,
    UPLOAD_MIN_CHUNKS,
    ChangeEntry,
    ChangeQuery,
    ChunkRow,
    WindowTooBusy,
)

BURST_BUCKET_MS = MARGIN_MS
BURST_MIN_WRITES = -(-UPLOAD_MIN_CHUNKS // 2)
assert (UPLOAD_MIN_CHUNKS - 1) * UPLOAD_GAP_MS < BURST_BUCKET_MS

# (from_ms, to_ms, only this robot or None) -> the (robot_id, bucket start) of the
# BURST_BUCKET_MS buckets (start = ts // BURST_BUCKET_MS * BURST_BUCKET_MS) holding at least
# BURST_MIN_WRITES of that robot's writes with from <= event time < to, and of every bucket
# holding a write of change_feed.UPLOADER_ID. Extra pairs (writes counted twice before a
# merge) only cost a read.
Bursts = Callable[[int, int, str | None], Iterable[tuple[str, int]]]
# (from_ms, to_ms, only these robots) -> their writes with from <= event time < to
Fetch = Callable[[int, int, Sequence[str]], Sequence[ChunkRow]]


def newest_first(query: ChangeQuery, bursts: Bursts, fetch: Fetch) -> list[ChangeEntry]:
    """`change_feed.page(every write of the span, query)` for a query of kind "upload"."""
    if query.kind != "upload":
        raise ValueError("upload_scan answers kind='upload' queries only")
    hi = query.to_ms if query.before is None else min(query.to_ms, query.before.ts_ms + 1)
    if hi <= query.from_ms:
        return []
    # An upload starting before `hi` has its first UPLOAD_MIN_CHUNKS writes before hi + MARGIN_MS.
    windows = _windows(bursts(query.from_ms, hi + MARGIN_MS, query.robot_id))
    found: dict[tuple[int, int, int, str], ChangeEntry] = {}
    read = 0
    for robot, lo, w_hi in windows:  # newest first
        # An upload listed from a later window starts before that window's end: once the
        # page is full of entries no older than this window's end, no later window adds one.
        if len(found) >= query.limit and sorted(found, reverse=True)[query.limit - 1][0] >= w_hi:
            break
        writes = _whole_runs(robot, lo, w_hi, fetch, query)
        read += len(writes)
        if read > change_feed.MAX_WRITES:
            raise WindowTooBusy(query)
        for e in change_feed.page(writes, query):
            found[e.key()] = e
    return [found[k] for k in sorted(found, reverse=True)[: query.limit]]


def _windows(pairs: Iterable[tuple[str, int]]) -> list[tuple[str, int, int]]:
    """(robot, from, to): each robot's found buckets with MARGIN_MS around them, overlapping
    ones merged; the window ending last first."""
    by_robot: dict[str, list[int]] = {}
    for robot, start in pairs:
        by_robot.setdefault(robot, []).append(start)
    out: list[tuple[str, int, int]] = []
    for robot, starts in by_robot.items():
        merged: list[list[int]] = []
        for s in sorted(set(starts)):
            lo, hi = s - MARGIN_MS, s + BURST_BUCKET_MS + MARGIN_MS
            if merged and lo <= merged[-1][1]:
                merged[-1][1] = hi
            else:
                merged.append([lo, hi])
        out += [(robot, lo, hi) for lo, hi in merged]
    return sorted(out, key=lambda w: (w[2], w[0]), reverse=True)


def _whole_runs(robot: str, lo: int, hi: int, fetch: Fetch, query: ChangeQuery) -> list[ChunkRow]:
    """The robot's writes in [lo, hi), widened until no run of them reaches an edge."""
    writes = list(fetch(lo, hi, [robot]))
    step = MARGIN_MS
    while writes and writes[0].ts_ms - UPLOAD_GAP_MS < lo:  # a run may begin before lo
        before = list(fetch(lo - step, lo, [robot]))
        writes[:0] = before
        lo, step = lo - step, step * 2
        if len(writes) > change_feed.MAX_WRITES:
            raise WindowTooBusy(query)
        if not before:
            break
    step = MARGIN_MS
    while writes and writes[-1].ts_ms + UPLOAD_GAP_MS >= hi:  # a run may go on after hi
        after = list(fetch(hi, hi + step, [robot]))
        writes += after
        hi, step = hi + step, step * 2
        if len(writes) > change_feed.MAX_WRITES:
            raise WindowTooBusy(query)
        if not after:
            break
    return writes
