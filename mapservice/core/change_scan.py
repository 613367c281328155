"""The change feed read newest first in time slices, so a page costs what it shows, not
the span (pure: the stores pass their two reads in).

Before, a store fetched every write of the span (plus margins) and `change_feed.page` kept
the newest 100 entries: a 1 h span of 200 robots was ~150,000 writes read FINAL and folded
in Python for a first page (p95 3.5 s), a day was refused. Here the span is cut from its
end (or from the page cursor) into slices, each handed to `change_feed.page` as its own
window with the same margins, until the page is full: the first slice is a minute, later
ones grow while few writes come back.

The answer is the one `page` gives for the whole span: the rule classifies a write from
the writes within `MARGIN_MS` of it, which every slice fetches (a run of writes no more
than `UPLOAD_GAP_MS` apart that reaches `MARGIN_MS` past the slice holds at least
`UPLOAD_MIN_CHUNKS` writes there, so it is an upload either way); an upload entry is
reported by the slice holding its first write; and an upload still going on at the end
of a slice's fetch is followed (that robot's writes only) until it ends, so its size and
last write are whole (the whole-span read cut them at the span's end margin).

Each request reads at most `change_feed.MAX_WRITES` writes in all: a page that is not full by then
(a rare robot or a small area over a long, busy span) is refused with what to do.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence

import msgspec

from mapservice.core import change_feed
from mapservice.core.change_feed import (
    MARGIN_MS,
    UPLOAD_GAP_MS,
    ChangeEntry,
    ChangeQuery,
    ChunkRow,
    WindowTooBusy,
)

FIRST_SLICE_MS = 60_000
# A slice grows at most this much at once, and towards this many writes.
GROWTH = 8
SLICE_WRITES = 20_000

# (from_ms, to_ms, only these robots or None) -> the writes with from <= event time < to
Fetch = Callable[[int, int, Collection[str] | None], Sequence[ChunkRow]]
# (chunks, before_ms) -> per chunk, the content hash of its latest write before before_ms
Earlier = Callable[[set[tuple[int, int]], int], Mapping[tuple[int, int], str]]


def newest_first(
    query: ChangeQuery, fetch: Fetch, earlier: Earlier, first_slice_ms: int = FIRST_SLICE_MS
) -> list[ChangeEntry]:
    """`change_feed.page(every write of the span, query, ...)`, read slice by slice."""
    hi = query.to_ms if query.before is None else min(query.to_ms, query.before.ts_ms + 1)
    out: list[ChangeEntry] = []
    span, read = first_slice_ms, 0
    while hi > query.from_ms and len(out) < query.limit:
        lo = max(query.from_ms, hi - span)
        part = msgspec.structs.replace(query, from_ms=lo, to_ms=hi, limit=query.limit - len(out))
        f_lo, f_hi = change_feed.fetch_window(part)
        writes = list(fetch(f_lo, f_hi, None))
        writes += _uploads_going_on(writes, part, f_hi, fetch)
        read += len(writes)
        if read > change_feed.MAX_WRITES:
            raise WindowTooBusy(query)
        out += change_feed.page(
            writes, part, earlier(change_feed.chunks_needing_earlier(writes, part), f_lo)
        )
        # Towards SLICE_WRITES writes a slice, growing at most GROWTH times.
        rate = max(len(writes), 1) / (hi - lo + 2 * MARGIN_MS)
        span = int(min(span * GROWTH, max(span, SLICE_WRITES / rate - 2 * MARGIN_MS)))
        hi = lo
    return out


def _uploads_going_on(
    writes: list[ChunkRow], part: ChangeQuery, end_ms: int, fetch: Fetch
) -> list[ChunkRow]:
    """The writes after `end_ms` of the uploads starting in `part` that had not ended by
    then (their writer wrote within UPLOAD_GAP_MS of it), fetched for those writers only."""
    more: list[ChunkRow] = []
    while True:
        runs = change_feed.upload_runs([*writes, *more])
        going = {
            last.robot_id
            for first, last, _ in runs
            if part.from_ms <= first.ts_ms < part.to_ms and last.ts_ms >= end_ms - UPLOAD_GAP_MS
        }
        if not going:
            return more
        step = max(MARGIN_MS, end_ms - part.from_ms)  # the reach doubles
        more += fetch(end_ms, end_ms + step, going)
        if len(more) > change_feed.MAX_WRITES:
            raise WindowTooBusy(msgspec.structs.replace(part, to_ms=end_ms + step))
        end_ms += step
