"""Recording conflicts after stored batches: the pure rule (`mapservice.core.conflicts`)
applied to the new writes and their stored neighbours (`find_conflicts`), the result
written to the store (`write_conflicts`), at once or several batches' worth together."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol

from mapservice.core.conflicts import RecentWrites, affected_conflicts, conflict_key, neighbourhoods
from mapservice.core.ports import ChunkRow, ConflictReader, ConflictRow, HistoryWriter


class ConflictStore(ConflictReader, HistoryWriter, Protocol):
    """What recording conflicts needs: the stored neighbours and the conflicts' writer."""


def record_conflicts(
    store: ConflictStore, new: list[ChunkRow], window_ms: int, recent: RecentWrites | None = None
) -> int:
    """After `new` writes are stored: writes every conflict they create or change;
    returns how many rows it wrote. Blocking: call from the store's thread."""
    return write_conflicts(store, find_conflicts(store, new, window_ms, recent), recent)


def find_conflicts(
    store: ConflictReader, new: list[ChunkRow], window_ms: int, recent: RecentWrites | None = None
) -> list[ConflictRow]:
    """After `new` writes are stored: every conflict they create or change, except rows
    `recent` saw written unchanged. Neighbours come from `recent` where it covers them,
    else from the store (blocking: call from the store's thread)."""
    if not new:
        return []
    if recent is not None:
        recent.add(new)
        if recent.covers(min(w.ts_ms for w in new) - window_ms):
            # A live batch: every neighbour is in the index, already sorted.
            return recent.unrecorded(recent.affected(new, window_ms))
    stored: list[ChunkRow] = []
    for chunks, lo, hi in neighbourhoods(new, window_ms):
        if recent is not None and recent.covers(lo):
            stored.extend(recent.near(chunks, lo, hi))
        else:
            stored.extend(store.chunk_writes_near(chunks, lo, hi))
    rows = affected_conflicts(new, stored + new, window_ms)
    return rows if recent is None else recent.unrecorded(rows)


def write_conflicts(
    store: HistoryWriter, rows: list[ConflictRow], recent: RecentWrites | None = None
) -> int:
    """Stores `rows` (found by `find_conflicts`) and tells `recent` they are written;
    returns how many."""
    store.append_conflicts(rows)
    if recent is not None:
        recent.mark_recorded(rows)
    return len(rows)


class UnwrittenConflicts:
    """Conflict rows found but not stored yet, one per identity: a later finding of the
    same conflict replaces an earlier one (the rule only ever moves a conflict's A to a
    later write, and each finding sees every write stored before it)."""

    def __init__(self) -> None:
        self._rows: dict[tuple, ConflictRow] = {}

    def __len__(self) -> int:
        return len(self._rows)

    def add(self, rows: Iterable[ConflictRow]) -> None:
        for c in rows:
            self._rows[conflict_key(c)] = c

    def rows(self) -> list[ConflictRow]:
        return [self._rows[k] for k in sorted(self._rows)]

    def clear(self) -> None:
        self._rows.clear()
