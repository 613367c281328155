"""Recording conflicts after stored batches: the pure rule (`mapservice.core.conflicts`)
applied to the new writes and their stored neighbours (`find_conflicts`), the result
written to the store (`write_conflicts`), at once or several batches' worth together
(`ConflictWatch`, the live views' part: the recent writes in memory and the rows found
but not yet written)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Protocol

from prometheus_client import Counter, Histogram

from mapservice.core.conflicts import RecentWrites, affected_conflicts, conflict_key, neighbourhoods
from mapservice.core.events import Envelope
from mapservice.core.ports import (
    ChunkRow,
    ConflictReader,
    ConflictRow,
    HistoryWriter,
    TimeTravelReader,
    chunk_rows_of,
)

CONFLICTS = Counter("mapservice_conflicts_recorded_total", "Conflict rows written to the history")
# Both on the store thread, where the next batch waits for them.
CONFLICT_CHECK_SECONDS = Histogram(
    "mapservice_conflicts_check_seconds",
    "Duration of finding one stored batch's conflicts",
    buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1),
)
CONFLICT_WRITE_SECONDS = Histogram(
    "mapservice_conflicts_write_seconds",
    "Duration of one insert of the conflicts found since the last",
    buckets=(0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1),
)
# Conflict neighbours of live batches come from memory (mapservice.core.conflicts.RecentWrites)
# when the window is short enough to keep its writes; older ones from the store.
RECENT_MAX_WINDOW_MS = 600_000
RECENT_SLACK_MS = 120_000
RECENT_MAX_ROWS = 200_000


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


class ConflictWatch:
    """Finds each stored batch's conflicts (`find`) and stores them several batches' worth
    at a time (`write`). Touched only in the store thread: `load` and `find` read the store
    (the writes near new ones from `conflicts`, the recent ones from `history`)."""

    def __init__(
        self,
        history: TimeTravelReader,
        conflicts: ConflictReader,
        writer: HistoryWriter,
        window_ms: int,
        now_ms: Callable[[], int],
    ) -> None:
        self.history, self.conflicts, self.writer = history, conflicts, writer
        self.window_ms = window_ms
        self.now_ms = now_ms
        self.recent: RecentWrites | None = None
        self.unwritten = UnwrittenConflicts()
        self._recent_pruned_ms = 0

    def _recent_span_ms(self) -> int:
        return 2 * self.window_ms + RECENT_SLACK_MS

    def load(self, horizon_ms: int) -> None:
        """The writes of the recent past in memory, when the window is short enough and
        they are few enough; else every batch asks the store."""
        self.recent = None
        if self.window_ms > RECENT_MAX_WINDOW_MS:
            return
        now = self.now_ms()
        since = now - self._recent_span_ms()
        rows = self.history.chunk_events(since, horizon_ms, limit=RECENT_MAX_ROWS)
        if len(rows) >= RECENT_MAX_ROWS:
            return  # too busy to hold in memory: every batch asks the store
        self._recent_pruned_ms = now
        self.recent = RecentWrites(since, rows)

    def find(self, events: Sequence[Envelope]) -> int:
        """Finds every conflict the stored batch creates or changes, for `write`; returns
        how many rows now wait to be written."""
        new = chunk_rows_of(events)
        now = self.now_ms()
        if self.recent is not None and now - self._recent_pruned_ms > 10_000:
            self.recent.forget_before(now - self._recent_span_ms())
            self._recent_pruned_ms = now
        with CONFLICT_CHECK_SECONDS.time():
            self.unwritten.add(find_conflicts(self.conflicts, new, self.window_ms, self.recent))
        return len(self.unwritten)

    def write(self) -> int:
        """Stores the conflicts found since the last call; returns how many rows."""
        if not self.unwritten:
            return 0
        rows = self.unwritten.rows()
        with CONFLICT_WRITE_SECONDS.time():
            write_conflicts(self.writer, rows, self.recent)
        self.unwritten.clear()
        CONFLICTS.inc(len(rows))
        return len(rows)
