"""Conflicts (the 2019 document's idea I.4): the rule as pure functions, which the
processors apply after each stored batch (`processors/conflict_recorder.py`).

The rule: writes A and B to the same chunk conflict when different robots wrote them,
their contents differ and their event times are at most the window apart. B is the
later of the two in (event time, robot id) order; the conflict's time is B's. Per B
there is one conflict (the table's identity is B's: (ts, row, column, robot_b)): it names
the latest write, in (event time, robot id) order, that conflicts with B. One row per
later write bounds the table by the chunk events (the 2019 load test, where every write
conflicts with several others, stored one row per pair at ~6 MB per robot-day); the other
writes of the window, and the contents of both, are in `chunk_events`.

A map upload is no conflict: a write by the map uploader (`UPLOADER_ID`, the robot id that
`mapservice up`'s start-up upload, `mapservice map upload` and the 2019 REST map upload write
as) is never A or B. The upload writes the whole map at one instant to seed the floor, so
it disagrees with every robot that saw the floor within the window (the simulator at
start-up) without anyone having changed anything; the change feed shows it as one `upload`
entry (mapservice/core/change_feed.py). Robots' writes around it conflict among themselves
as before, the upload's writes skipped.

The rule is monotonic: a late or re-delivered write can only add conflicts or move a
conflict's A to a later write, never remove one. So recomputing the conflicts of every
write a batch touches, from everything stored so far, converges on exactly the answer a
fold of the whole history gives, whatever the arrival order (and a repeat writes the
same rows again).
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from collections import defaultdict
from collections.abc import Iterable

from mapservice.core.change_feed import UPLOADER_ID
from mapservice.core.ports import ChunkRow, ConflictRow

# A write's identity: (event time, row, column, robot id).
Identity = tuple[int, int, int, str]


def is_upload(w: ChunkRow) -> bool:
    """Whether the write is part of a map upload (the map uploader's), never in a conflict."""
    return w.robot_id == UPLOADER_ID


def _order(w: ChunkRow) -> tuple[int, str]:
    return (w.ts_ms, w.robot_id)


def conflicts_of(b: ChunkRow, writes: Iterable[ChunkRow], window_ms: int) -> list[ConflictRow]:
    """The conflict whose later write is `b`, among `writes` (any chunks; others
    ignored): none, or one naming the latest conflicting write."""
    best: ChunkRow | None = None
    if is_upload(b):
        return []
    for a in writes:
        if (a.row, a.column) != (b.row, b.column) or a.robot_id == b.robot_id or is_upload(a):
            continue
        if a.content_hash == b.content_hash or _order(a) >= _order(b):
            continue
        if b.ts_ms - a.ts_ms > window_ms:
            continue
        if best is None or _order(a) > _order(best):
            best = a
    if best is None:
        return []
    return [ConflictRow(b.row, b.column, b.ts_ms, best.robot_id, best.ts_ms, b.robot_id)]


def all_conflicts(writes: Iterable[ChunkRow], window_ms: int) -> list[ConflictRow]:
    """Brute force over a whole history (what the incremental path must agree with)."""
    by_chunk: dict[tuple[int, int], list[ChunkRow]] = defaultdict(list)
    for w in _unique(writes):
        by_chunk[(w.row, w.column)].append(w)
    out = [
        c for chunk in by_chunk.values() for b in chunk for c in conflicts_of(b, chunk, window_ms)
    ]
    return sorted(out, key=conflict_key)


def affected_conflicts(
    new: Iterable[ChunkRow], stored: Iterable[ChunkRow], window_ms: int
) -> list[ConflictRow]:
    """Every conflict a batch of new writes can create or change, given `stored` (which
    holds the batch and every write within the window of it on the same chunks).

    A new write matters as B (its own conflicts) and as A (for later writes of other
    robots within the window, whose conflict with its robot it may create or move).
    Per chunk the writes are sorted in (event time, robot id) order, so both lookups
    scan only the window next to a write instead of every write of its chunk (the 2019
    load test keeps ~130 writes per chunk within the window).
    """
    by_chunk = _by_chunk(stored)
    out: dict[Identity, ConflictRow] = {}
    for chunk, news in _by_chunk(new).items():
        writes = sorted(by_chunk.get(chunk, ()), key=_order)
        _affected_in_chunk(news, writes, [_order(w) for w in writes], window_ms, out)
    return [out[k] for k in sorted(out)]


def _by_chunk(writes: Iterable[ChunkRow]) -> dict[tuple[int, int], list[ChunkRow]]:
    out: dict[tuple[int, int], list[ChunkRow]] = defaultdict(list)
    for w in _unique(writes):
        out[(w.row, w.column)].append(w)
    return out


def _affected_in_chunk(
    news: list[ChunkRow],
    writes: list[ChunkRow],
    keys: list[tuple[int, str]],
    window_ms: int,
    out: dict[Identity, ConflictRow],
) -> None:
    """`affected_conflicts` for one chunk: `writes` (sorted by `_order`, whose keys are
    `keys`) hold the new writes and their neighbours; the conflicts go into `out`."""
    bs: dict[Identity, ChunkRow] = {}
    for n in news:
        bs[_identity(n)] = n
        i = bisect_right(keys, _order(n))
        while i < len(writes):
            w = writes[i]
            if w.ts_ms - n.ts_ms > window_ms:
                break
            if w.robot_id != n.robot_id:
                bs[_identity(w)] = w
            i += 1
    for b in bs.values():
        c = _latest_conflict(b, writes, keys, window_ms)
        if c is not None:
            out[conflict_key(c)] = c


def _latest_conflict(
    b: ChunkRow, writes: list[ChunkRow], keys: list[tuple[int, str]], window_ms: int
) -> ConflictRow | None:
    """`conflicts_of(b, writes)` for one chunk's writes sorted by `_order` (keys)."""
    if is_upload(b):
        return None
    i = bisect_left(keys, _order(b))
    while i > 0:
        i -= 1
        a = writes[i]
        if b.ts_ms - a.ts_ms > window_ms:
            return None
        if a.robot_id != b.robot_id and a.content_hash != b.content_hash and not is_upload(a):
            return ConflictRow(b.row, b.column, b.ts_ms, a.robot_id, a.ts_ms, b.robot_id)
    return None


def neighbourhoods(
    new: Iterable[ChunkRow], window_ms: int
) -> list[tuple[list[tuple[int, int]], int, int]]:
    """What to read from the store for `affected_conflicts`: clusters of the batch in
    time (a robot's old backlog and live writes stay separate reads), each as (chunks,
    from_ms, to_ms) covering every write within the window of the cluster's writes."""
    writes = sorted(new, key=lambda w: w.ts_ms)
    clusters: list[list[ChunkRow]] = []
    for w in writes:
        if clusters and w.ts_ms - clusters[-1][-1].ts_ms <= 2 * window_ms:
            clusters[-1].append(w)
        else:
            clusters.append([w])
    return [
        (sorted({(w.row, w.column) for w in c}), c[0].ts_ms - window_ms, c[-1].ts_ms + window_ms)
        for c in clusters
    ]


class _ChunkWrites:
    """One chunk's writes sorted in (event time, robot id) order, one per identity (within a
    chunk that order is the identity): what `_affected_in_chunk` scans, kept sorted as
    writes arrive instead of sorted again for every batch."""

    __slots__ = ("keys", "writes")

    def __init__(self) -> None:
        self.keys: list[tuple[int, str]] = []
        self.writes: list[ChunkRow] = []

    def put(self, w: ChunkRow) -> None:
        key = _order(w)
        i = bisect_left(self.keys, key)
        if i < len(self.keys) and self.keys[i] == key:
            self.writes[i] = w  # the same write again: the last one counts, as in the history
        else:
            self.keys.insert(i, key)
            self.writes.insert(i, w)

    def between(self, from_ms: int, to_ms: int) -> list[ChunkRow]:
        return self.writes[
            bisect_left(self.keys, (from_ms,)) : bisect_left(self.keys, (to_ms + 1,))
        ]

    def forget_before(self, ts_ms: int) -> None:
        i = bisect_left(self.keys, (ts_ms,))
        del self.keys[:i], self.writes[:i]


class RecentWrites:
    """The writes this processor stored with event time >= `covered_from_ms`, per chunk:
    a live batch (event times near now) finds its neighbours here instead of querying the
    store. Complete only while every write of these chunks goes through its owner (faust
    gives each chunk's partition to one processor; the owner loads it at assignment)."""

    def __init__(self, covered_from_ms: int, rows: Iterable[ChunkRow] = ()) -> None:
        self.covered_from_ms = covered_from_ms
        self._by_chunk: dict[tuple[int, int], _ChunkWrites] = defaultdict(_ChunkWrites)
        # Conflict rows this processor wrote: recomputed unchanged, they are not written again.
        self._recorded: dict[Identity, ConflictRow] = {}
        self.add(rows)

    def unrecorded(self, rows: Iterable[ConflictRow]) -> list[ConflictRow]:
        return [c for c in rows if self._recorded.get(conflict_key(c)) != c]

    def mark_recorded(self, rows: Iterable[ConflictRow]) -> None:
        for c in rows:
            self._recorded[conflict_key(c)] = c

    def add(self, rows: Iterable[ChunkRow]) -> None:
        for w in rows:
            if w.ts_ms >= self.covered_from_ms:
                self._by_chunk[(w.row, w.column)].put(w)

    def covers(self, from_ms: int) -> bool:
        return from_ms >= self.covered_from_ms

    def near(self, chunks: Iterable[tuple[int, int]], from_ms: int, to_ms: int) -> list[ChunkRow]:
        return [
            w
            for c in chunks
            if c in self._by_chunk
            for w in self._by_chunk[c].between(from_ms, to_ms)
        ]

    def affected(self, new: Iterable[ChunkRow], window_ms: int) -> list[ConflictRow]:
        """`affected_conflicts(new, <every write of their chunks>)` from the sorted index,
        for a batch already `add`ed whose writes it covers to the window before the first:
        a live batch costs its own writes' scans, not a sort of every write of the window."""
        out: dict[Identity, ConflictRow] = {}
        for chunk, news in _by_chunk(new).items():
            writes = self._by_chunk[chunk]
            _affected_in_chunk(news, writes.writes, writes.keys, window_ms, out)
        return [out[k] for k in sorted(out)]

    def forget_before(self, ts_ms: int) -> None:
        """Drops writes older than `ts_ms` (the index then covers only from there)."""
        if ts_ms <= self.covered_from_ms:
            return
        self.covered_from_ms = ts_ms
        for chunk in list(self._by_chunk):
            writes = self._by_chunk[chunk]
            writes.forget_before(ts_ms)
            if not writes.writes:
                del self._by_chunk[chunk]
        self._recorded = {k: c for k, c in self._recorded.items() if c.ts_ms >= ts_ms}

    def __len__(self) -> int:
        return sum(len(v.writes) for v in self._by_chunk.values())


def conflict_key(c: ConflictRow) -> tuple[int, int, int, str]:
    """The natural identity, B's (and the order of the `conflicts` table)."""
    return (c.ts_ms, c.row, c.column, c.robot_b)


def _identity(w: ChunkRow) -> Identity:
    return (w.ts_ms, w.row, w.column, w.robot_id)


def _unique(writes: Iterable[ChunkRow]) -> Iterable[ChunkRow]:
    """One write per natural identity (the last one, as the history keeps it)."""
    return {_identity(w): w for w in writes}.values()
