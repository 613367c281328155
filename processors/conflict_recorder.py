"""Recording conflicts after each stored batch: the pure rule (`mapservice.core.conflicts`)
applied to the new writes and their stored neighbours, the result written to the store."""

from __future__ import annotations

from mapservice.core.conflicts import RecentWrites, affected_conflicts, neighbourhoods
from mapservice.core.ports import ChunkRow, ConflictRow, HistoryStore


def record_conflicts(store: HistoryStore, new: list[ChunkRow], window_ms: int,
                     recent: RecentWrites | None = None) -> int:
    """After `new` writes are stored: writes every conflict they create or change;
    returns how many rows it wrote. Blocking: call from the store's thread. Neighbours
    come from `recent` where it covers them, else from the store; rows `recent` saw
    written unchanged are not written again."""
    if not new:
        return 0
    if recent is not None:
        recent.add(new)
        if recent.covers(min(w.ts_ms for w in new) - window_ms):
            # A live batch: every neighbour is in the index, already sorted.
            return _write_unrecorded(store, recent, recent.affected(new, window_ms))
    stored: list[ChunkRow] = []
    for chunks, lo, hi in neighbourhoods(new, window_ms):
        if recent is not None and recent.covers(lo):
            stored.extend(recent.near(chunks, lo, hi))
        else:
            stored.extend(store.chunk_writes_near(chunks, lo, hi))
    return _write_unrecorded(store, recent, affected_conflicts(new, stored + new, window_ms))


def _write_unrecorded(store: HistoryStore, recent: RecentWrites | None,
                      rows: list[ConflictRow]) -> int:
    if recent is not None:
        rows = recent.unrecorded(rows)
    store.append_conflicts(rows)
    if recent is not None:
        recent.mark_recorded(rows)
    return len(rows)
