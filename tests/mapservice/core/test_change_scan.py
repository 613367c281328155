"""The change feed read newest first in slices (core/change_scan.py) gives the page the
rule gives for the whole span (core/change_feed.page over every write), for random
histories with uploads crossing slice edges, areas, robots, kinds and cursors; it reads a
minute, not the span, for a first page; and it follows an upload that outlasts a slice."""

from __future__ import annotations

import random

import pytest

from mapservice.core import change_feed, change_scan
from mapservice.core.change_feed import (
    UPLOADER_ID,
    ChangeCursor,
    ChangeQuery,
    ChunkBox,
    WindowTooBusy,
)
from mapservice.core.ports import ChunkRow

T0 = 1_700_000_000_000


def _history(seed: int) -> list[ChunkRow]:
    rng = random.Random(seed)
    rows: list[ChunkRow] = []
    for _ in range(600):  # robots' writes, a few distinct contents so some change nothing
        rows.append(
            ChunkRow(
                rng.randrange(4),
                rng.randrange(5),
                T0 + rng.randrange(3_600_000),
                f"r{rng.randrange(4)}",
                f"{rng.randrange(3):032x}",
                0,
            )
        )
    for _ in range(8):  # uploads: bursts of 20-70 writes at most a second apart
        t, robot = T0 + rng.randrange(3_600_000), rng.choice(["r1", "up", UPLOADER_ID])
        for i in range(rng.randrange(20, 70)):
            t += rng.randrange(0, 1_000)
            rows.append(ChunkRow(i // 5 % 4, i % 5, t, robot, f"{10 + i % 7:032x}", 0))
    return sorted(set(rows), key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))


class _Reads:
    def __init__(self, rows: list[ChunkRow]) -> None:
        self.rows, self.fetched = rows, 0

    def fetch(self, lo: int, hi: int, robots=None) -> list[ChunkRow]:
        out = [
            r for r in self.rows if lo <= r.ts_ms < hi and (robots is None or r.robot_id in robots)
        ]
        self.fetched += len(out)
        return out

    def earlier(self, chunks, before_ms: int) -> dict[tuple[int, int], str]:
        last: dict[tuple[int, int], tuple[int, str, str]] = {}
        for r in self.rows:
            k = (r.row, r.column)
            if (
                r.ts_ms < before_ms
                and k in chunks
                and (r.ts_ms, r.robot_id) > last.get(k, (-1, ""))[:2]
            ):
                last[k] = (r.ts_ms, r.robot_id, r.content_hash)
        return {k: v[2] for k, v in last.items()}


def _whole(reads: _Reads, q: ChangeQuery) -> list:
    lo, hi = change_feed.fetch_window(q)
    writes = reads.fetch(lo, hi)
    return change_feed.page(
        writes, q, reads.earlier(change_feed.chunks_needing_earlier(writes, q), lo)
    )


@pytest.mark.parametrize("seed", range(6))
def test_slices_give_the_whole_spans_page(seed: int) -> None:
    reads = _Reads(_history(seed))
    rng = random.Random(seed)
    # Spans ending over a minute before the last write: no upload is cut at the span's end
    # margin, where the whole-span read cut it and the slices follow it.
    for q in [
        ChangeQuery(T0, T0 + 3_000_000, limit=1000),
        ChangeQuery(T0 + 600_000, T0 + 2_400_000, limit=7),
        ChangeQuery(T0, T0 + 3_000_000, robot_id="r1", limit=20),
        ChangeQuery(T0, T0 + 3_000_000, box=ChunkBox(1, 2, 0, 2), limit=15),
        ChangeQuery(T0, T0 + 3_000_000, kind="upload", limit=50),
        ChangeQuery(T0, T0 + 3_000_000, kind="change", limit=3),
    ]:
        want = _whole(reads, q)
        assert change_scan.newest_first(q, reads.fetch, reads.earlier) == want
        if want:  # and from a cursor in the middle
            k = want[rng.randrange(len(want))].key()
            paged = ChangeQuery(
                q.from_ms, q.to_ms, q.robot_id, q.box, ChangeCursor(*k), q.limit, q.kind
            )
            assert change_scan.newest_first(paged, reads.fetch, reads.earlier) == _whole(
                reads, paged
            )


def test_a_first_page_reads_the_newest_minutes_not_the_span() -> None:
    rows = [ChunkRow(i % 4, i % 5, T0 + 500 * i, f"r{i % 7}", f"{i:032x}", 0) for i in range(7_200)]
    reads = _Reads(rows)
    q = ChangeQuery(T0, T0 + 3_600_000, limit=100)
    assert change_scan.newest_first(q, reads.fetch, reads.earlier) == _whole(reads, q)
    reads.fetched = 0
    change_scan.newest_first(q, reads.fetch, reads.earlier)
    assert reads.fetched < 400  # of 7,200 writes: the last minute and its margins


def test_an_upload_outlasting_a_slice_is_followed_to_its_end() -> None:
    """A 2019 robot re-sending its map for 5 minutes, a write every 900 ms: one upload with
    every write counted, though the slice holding its first write (the page before ended
    just after it) fetches only 20 s past it."""
    loop = [ChunkRow(i % 3, i % 4, T0 + 900 * i, "looping", f"{i % 9:032x}", 0) for i in range(334)]
    reads = _Reads(loop)
    q = ChangeQuery(T0 - 60_000, T0 + 3_600_000, before=ChangeCursor(T0 + 500, 0, 0, "a"), limit=10)
    entries = change_scan.newest_first(q, reads.fetch, reads.earlier, first_slice_ms=1_000)
    assert [(e.kind, e.robot_id, e.chunks, e.end_ms) for e in entries] == [
        ("upload", "looping", 334, T0 + 900 * 333)
    ]
    assert reads.fetched < 1_000


def test_a_page_not_full_within_the_read_budget_is_refused(monkeypatch) -> None:
    monkeypatch.setattr(change_feed, "MAX_WRITES", 1_000)
    rows = [ChunkRow(0, i % 5, T0 + 2000 * i, "r0", f"{i % 2:032x}", 0) for i in range(1_500)]
    reads = _Reads(rows)
    with pytest.raises(WindowTooBusy, match="shorter span"):
        change_scan.newest_first(
            ChangeQuery(T0, T0 + 3_000_000, robot_id="nobody"), reads.fetch, reads.earlier
        )
    # A page that fills early reads little and is served.
    assert (
        len(
            change_scan.newest_first(
                ChangeQuery(T0, T0 + 3_000_000, limit=5), reads.fetch, reads.earlier
            )
        )
        == 5
    )
