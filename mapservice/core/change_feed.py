"""The change feed: a window's map changes, newest first, with map uploads folded into one
entry each (pure; the stores fetch the writes, this module decides what they are).

The upload rule: a writer's *run* is its chunk writes with no gap longer than
`UPLOAD_GAP_MS` between consecutive ones (over the whole map, whatever area is asked for).
A run of at least `UPLOAD_MIN_CHUNKS` writes is a map upload (the start-up upload of the
whole floor, a robot re-sending its map): it is one `upload` entry at the run's first
write, carrying how many chunks it wrote, and none of its writes is a floor change. Every
other write that changes the chunk's content is a `change` entry with the chunk's previous
content hash (the write before it by (event time, robot id), map_at's order), for
before/after thumbnails; a write that leaves the content as it was (a robot re-sending the
chunk it sees) is no change and is left out. The floor upload `mapservice up` publishes
carries one timestamp for every chunk, a 2019 robot re-sending its map sends them in a
loop: both are far inside the gap, while robots reporting changes (or re-sending a chunk
every few seconds, as the 2019 load test did) are not. The map uploader's writes
(`UPLOADER_ID`, what `mapservice up` and `mapservice map upload` write as) are an
upload whatever their number: a one-chunk map is still an upload, and never a conflict.

Because a run is decided on its whole extent, the stores fetch the writes from
`UPLOAD_GAP_MS * UPLOAD_MIN_CHUNKS` before the window to as long after it: any run reaching
into the window and long enough to be an upload is seen whole.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Protocol

import msgspec


class ChunkRow(Protocol):
    """A chunk write as the stores return it (ports.ChunkRow; not imported: ports names
    this module's types)."""

    row: int
    column: int
    ts_ms: int
    robot_id: str
    content_hash: str


# The robot id map uploads write as (`mapservice up`, `mapservice map upload`, the 2019 REST
# upload through them); the conflict rule leaves its writes out.
UPLOADER_ID = "map-upload"
UPLOAD_GAP_MS = 1_000
UPLOAD_MIN_CHUNKS = 20
MARGIN_MS = UPLOAD_GAP_MS * UPLOAD_MIN_CHUNKS
# The most writes a store hands to `page` for one request: the rule runs here, over every
# write of the window, so a window holding more (a week of a large fleet re-sending chunks)
# is refused with what to do instead of holding a read client for minutes.
MAX_WRITES = 300_000


class WindowTooBusy(ValueError):
    """The window holds more than MAX_WRITES chunk writes."""

    def __init__(self, query: ChangeQuery) -> None:
        hours = (query.to_ms - query.from_ms) / 3_600_000
        super().__init__(
            f"the {hours:.1f} h window holds more than {MAX_WRITES:,} chunk writes, more than "
            "the change feed reads at once; choose a shorter span (zoom the timeline in)"
        )


class ChunkBox(msgspec.Struct, frozen=True):
    """Chunks with row_min <= row <= row_max and col_min <= column <= col_max."""

    row_min: int
    row_max: int
    col_min: int
    col_max: int

    def holds(self, row: int, column: int) -> bool:
        return self.row_min <= row <= self.row_max and self.col_min <= column <= self.col_max


class ChangeCursor(msgspec.Struct, frozen=True):
    """Where a page ended: the next page holds entries strictly older in the feed's order."""

    ts_ms: int
    row: int
    column: int
    robot_id: str

    def encode(self) -> str:
        return f"{self.ts_ms}:{self.row}:{self.column}:{self.robot_id}"

    @classmethod
    def decode(cls, text: str) -> ChangeCursor:
        """Raises ValueError on anything `encode` did not write."""
        ts, row, column, robot = text.split(":", 3)
        if not robot:
            raise ValueError("no robot id")
        return cls(int(ts), int(row), int(column), robot)


class ChangeQuery(msgspec.Struct, frozen=True):
    from_ms: int
    to_ms: int  # exclusive
    robot_id: str | None = None
    box: ChunkBox | None = None
    before: ChangeCursor | None = None
    limit: int = 100
    kind: str | None = (
        None  # "change" or "upload": only entries of that kind (the timeline's upload marks)
    )


class ChangeEntry(msgspec.Struct, frozen=True, gc=False):
    """A floor change (`kind` "change") or a map upload (`kind` "upload", at its first write;
    `row`/`column` are that write's, `chunks` how many it wrote, `end_ms` its last write)."""

    kind: str
    ts_ms: int
    row: int
    column: int
    robot_id: str
    content_hash: str
    previous_hash: str | None
    chunks: int = 1
    end_ms: int = 0

    def key(self) -> tuple[int, int, int, str]:
        return (self.ts_ms, self.row, self.column, self.robot_id)


def fetch_window(query: ChangeQuery) -> tuple[int, int]:
    """The writes a store hands to `page`: [from - margin, to + margin)."""
    return query.from_ms - MARGIN_MS, query.to_ms + MARGIN_MS


def _order(r: ChunkRow) -> tuple[int, str]:
    return (r.ts_ms, r.robot_id)


def page(
    writes: Iterable[ChunkRow],
    query: ChangeQuery,
    earlier: Mapping[tuple[int, int], str] | None = None,
) -> list[ChangeEntry]:
    """The feed's page for `query`, newest first, from `writes` = every robot's writes of
    `fetch_window(query)` and `earlier` = per chunk, the
    content hash of its latest write before that window (only the chunks the caller knows
    to need it: `chunks_needing_earlier`)."""
    rows = sorted(writes, key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))
    if len(rows) > MAX_WRITES:
        raise WindowTooBusy(query)
    upload_of = _uploads(rows)
    previous = _previous_hashes(rows, earlier or {})
    # An upload shows when any of its writes is in the area.
    uploads_in_area = {
        id(run[0])
        for r in rows
        if (run := upload_of.get(id(r))) is not None
        and (query.box is None or query.box.holds(r.row, r.column))
    }
    entries: list[ChangeEntry] = []
    seen_uploads: set[int] = set()
    for r in rows:
        if query.robot_id is not None and r.robot_id != query.robot_id:
            continue
        run = upload_of.get(id(r))
        if run is not None:
            first, last, n = run
            if (
                id(first) in seen_uploads
                or id(first) not in uploads_in_area
                or not query.from_ms <= first.ts_ms < query.to_ms
            ):
                continue
            seen_uploads.add(id(first))
            entries.append(
                ChangeEntry(
                    "upload",
                    first.ts_ms,
                    first.row,
                    first.column,
                    first.robot_id,
                    first.content_hash,
                    None,
                    n,
                    last.ts_ms,
                )
            )
        elif previous.get(id(r)) == r.content_hash:
            continue
        elif query.from_ms <= r.ts_ms < query.to_ms and (
            query.box is None or query.box.holds(r.row, r.column)
        ):
            entries.append(
                ChangeEntry(
                    "change",
                    r.ts_ms,
                    r.row,
                    r.column,
                    r.robot_id,
                    r.content_hash,
                    previous.get(id(r)),
                    1,
                    r.ts_ms,
                )
            )
    if query.kind is not None:
        entries = [e for e in entries if e.kind == query.kind]
    entries.sort(key=ChangeEntry.key, reverse=True)
    if query.before is not None:
        b = query.before
        limit_key = (b.ts_ms, b.row, b.column, b.robot_id)
        entries = [e for e in entries if e.key() < limit_key]
    return entries[: query.limit]


def chunks_needing_earlier(writes: Sequence[ChunkRow], query: ChangeQuery) -> set[tuple[int, int]]:
    """Chunks in the query's area whose first fetched write falls inside the window: their
    previous content lies before the fetched writes."""
    first: dict[tuple[int, int], int] = {}
    for r in writes:
        k = (r.row, r.column)
        first[k] = min(first.get(k, r.ts_ms), r.ts_ms)
    return {
        k
        for k, ts in first.items()
        if ts >= query.from_ms and (query.box is None or query.box.holds(*k))
    }


def upload_runs(rows: Sequence[ChunkRow]) -> list[tuple[ChunkRow, ChunkRow, int]]:
    """The (first, last, size) of each upload among `rows` (sorted by time)."""
    return list({id(run[0]): run for run in _uploads(rows).values()}.values())


def _uploads(rows: Sequence[ChunkRow]) -> dict[int, tuple[ChunkRow, ChunkRow, int]]:
    """id(write) -> (first, last, size) of its run, for the writes in runs that are uploads."""
    by_robot: dict[str, list[ChunkRow]] = {}
    for row in rows:
        by_robot.setdefault(row.robot_id, []).append(row)
    out: dict[int, tuple[ChunkRow, ChunkRow, int]] = {}
    for writes in by_robot.values():
        run: list[ChunkRow] = []
        ends: list[ChunkRow | None] = [*writes, None]  # None closes the last run
        for r in ends:
            if r is not None and (not run or r.ts_ms - run[-1].ts_ms <= UPLOAD_GAP_MS):
                run.append(r)
                continue
            if run and (len(run) >= UPLOAD_MIN_CHUNKS or run[0].robot_id == UPLOADER_ID):
                info = (run[0], run[-1], len(run))
                out.update((id(w), info) for w in run)
            run = [r] if r is not None else []
    return out


def _previous_hashes(
    rows: Sequence[ChunkRow], earlier: Mapping[tuple[int, int], str]
) -> dict[int, str | None]:
    """id(write) -> content hash of the write before it on its chunk (by time, robot)."""
    last: dict[tuple[int, int], str] = dict(earlier)
    out: dict[int, str | None] = {}
    for r in sorted(rows, key=_order):
        k = (r.row, r.column)
        out[id(r)] = last.get(k)
        last[k] = r.content_hash
    return out
