"""A span's uploads found from where writes bunch up (core/upload_scan.py) are the uploads
the rule gives over every write (core/change_feed.page), for random histories with
uploads of every size and pace, areas, robots and cursors; a week of busy writers is
answered by reading the uploads' writes, not the week; an upload longer than the margin
is followed to its end."""

from __future__ import annotations

import random

import pytest

from mapservice.core import change_feed, upload_scan
from mapservice.core.change_feed import (
    UPLOAD_GAP_MS,
    UPLOADER_ID,
    ChangeCursor,
    ChangeQuery,
    ChunkBox,
)
from mapservice.core.ports import ChunkRow

T0 = 1_700_000_020_000
DAY = 86_400_000


class _Reads:
    def __init__(self, rows: list[ChunkRow]) -> None:
        self.rows = sorted(set(rows), key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))
        self.fetched = 0

    def fetch(self, lo: int, hi: int, robots) -> list[ChunkRow]:
        out = [r for r in self.rows if lo <= r.ts_ms < hi and r.robot_id in robots]
        self.fetched += len(out)
        return out

    def bursts(self, lo: int, hi: int, robot: str | None) -> list[tuple[str, int]]:
        counts: dict[tuple[str, int], int] = {}
        b = upload_scan.BURST_BUCKET_MS
        for r in self.rows:
            if lo <= r.ts_ms < hi and robot in (None, r.robot_id):
                k = (r.robot_id, r.ts_ms // b * b)
                counts[k] = counts.get(k, 0) + 1
        return [
            k for k, n in counts.items() if n >= upload_scan.BURST_MIN_WRITES or k[0] == UPLOADER_ID
        ]

    def scan(self, q: ChangeQuery) -> list:
        return upload_scan.newest_first(q, self.bursts, self.fetch)

    def whole(self, q: ChangeQuery) -> list:
        """The rule over every write there is."""
        return change_feed.page(self.rows, q)


def _history(seed: int, span_ms: int) -> list[ChunkRow]:
    rng = random.Random(seed)
    rows = [
        ChunkRow(
            rng.randrange(4),
            rng.randrange(5),
            T0 + rng.randrange(span_ms),
            f"r{rng.randrange(4)}",
            f"{rng.randrange(3):032x}",
            0,
        )
        for _ in range(800)
    ]
    for _ in range(14):
        # Uploads (or bursts just short of one) of any pace up to the gap, by robots that
        # also write alone, and the map uploader's few writes.
        t, robot = T0 + rng.randrange(span_ms), rng.choice(["r1", "up", "r3", UPLOADER_ID])
        n = rng.choice([rng.randrange(1, 5), 19, 20, rng.randrange(20, 90)])
        pace = rng.choice([0, 100, UPLOAD_GAP_MS])
        for i in range(n):
            t += rng.randrange(0, pace + 1)
            rows.append(ChunkRow(i // 5 % 4, i % 5, t, robot, f"{10 + i % 7:032x}", 0))
    return rows


@pytest.mark.parametrize("seed", range(8))
def test_found_uploads_are_the_rules_uploads(seed: int) -> None:
    span = 2 * 3_600_000
    reads = _Reads(_history(seed, span))
    rng = random.Random(seed)
    for q in [
        ChangeQuery(T0 - DAY, T0 + 7 * DAY, kind="upload", limit=1000),
        ChangeQuery(T0 + 1_800_000, T0 + 5_400_000, kind="upload", limit=1000),
        ChangeQuery(T0, T0 + span, kind="upload", limit=3),
        ChangeQuery(T0, T0 + span, robot_id="r1", kind="upload", limit=50),
        ChangeQuery(T0, T0 + span, box=ChunkBox(2, 3, 0, 1), kind="upload", limit=50),
    ]:
        want = reads.whole(q)
        assert reads.scan(q) == want
        if want:  # and from a cursor in the middle
            k = want[rng.randrange(len(want))].key()
            paged = ChangeQuery(
                q.from_ms, q.to_ms, q.robot_id, q.box, ChangeCursor(*k), q.limit, q.kind
            )
            assert reads.scan(paged) == reads.whole(paged)
    assert reads.whole(
        ChangeQuery(T0 - DAY, T0 + DAY, kind="upload", limit=1000)
    )  # uploads to find


def test_a_busy_week_reads_the_uploads_writes_not_the_week(monkeypatch) -> None:
    """200 robots each writing a chunk a minute for a week (2 M writes, more than the change
    feed reads at once) and two uploads: both found, reading little more than their writes."""
    monkeypatch.setattr(change_feed, "MAX_WRITES", 5_000)

    class Busy(_Reads):
        """Every robot's week, generated per read: a write every 60 s, robot k at second k."""

        def fetch(self, lo, hi, robots):
            out = [r for r in self.rows if lo <= r.ts_ms < hi and r.robot_id in robots]
            for robot in robots:
                if robot.startswith("bot-"):
                    k = int(robot[4:])
                    first = lo + (T0 + 1000 * k - lo) % 60_000
                    out += [ChunkRow(1, 1, t, robot, "0" * 32, 0) for t in range(first, hi, 60_000)]
            self.fetched += len(out)
            return sorted(out, key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))

        # bursts: the stored rows' (a write a minute never reaches the threshold)

    floor = [
        ChunkRow(i // 17, i % 17, T0 + 2 * DAY + i // 50, UPLOADER_ID, f"{i:032x}", 0)
        for i in range(187)
    ]
    # bot-7 re-sends 40 chunks between its minute's writes (at 7 s and 67 s).
    resend = [
        ChunkRow(0, i % 3, T0 + 5 * DAY + 20_000 + 900 * i, "bot-7", f"{i:032x}", 0)
        for i in range(40)
    ]
    reads = Busy(floor + resend)
    q = ChangeQuery(T0, T0 + 7 * DAY, kind="upload", limit=1000)
    got = reads.scan(q)
    assert [(e.robot_id, e.chunks, e.ts_ms, e.end_ms) for e in got] == [
        ("bot-7", 40, T0 + 5 * DAY + 20_000, T0 + 5 * DAY + 20_000 + 900 * 39),
        (UPLOADER_ID, 187, T0 + 2 * DAY, T0 + 2 * DAY + 3),
    ]
    assert reads.fetched < 300  # of 2 M writes


def test_an_upload_longer_than_the_margin_is_followed_to_its_end() -> None:
    """A 2019 robot re-sending its map for 5 minutes, a write every 900 ms, started before
    the span: not listed (it starts before), and one that starts in it is listed whole."""
    loop = [ChunkRow(i % 3, i % 4, T0 + 900 * i, "looping", f"{i % 9:032x}", 0) for i in range(334)]
    reads = _Reads(loop)
    assert reads.scan(ChangeQuery(T0 + 60_000, T0 + DAY, kind="upload")) == []
    got = reads.scan(ChangeQuery(T0 - 60_000, T0 + 1000, kind="upload"))
    assert [(e.robot_id, e.chunks, e.end_ms) for e in got] == [("looping", 334, T0 + 900 * 333)]


def test_only_kind_upload_is_answered() -> None:
    with pytest.raises(ValueError, match="kind='upload'"):
        _Reads([]).scan(ChangeQuery(T0, T0 + DAY))


def test_an_upload_at_the_slowest_pace_across_a_bucket_edge_is_found() -> None:
    """20 writes exactly a gap apart, half in each of two buckets: still an upload."""
    start = T0 + 3 * upload_scan.BURST_BUCKET_MS - 10 * UPLOAD_GAP_MS
    reads = _Reads(
        [ChunkRow(0, i, start + UPLOAD_GAP_MS * i, "slow", f"{i:032x}", 0) for i in range(20)]
    )
    q = ChangeQuery(T0, T0 + DAY, kind="upload")
    assert (
        [(e.robot_id, e.chunks) for e in reads.scan(q)]
        == [("slow", 20)]
        == [(e.robot_id, e.chunks) for e in reads.whole(q)]
    )


def test_a_full_page_still_takes_a_newer_upload_read_later() -> None:
    """A long upload read first (its reads end last) starts before a short one read after
    it: a page of one is the short one, the newer start."""
    long_run = [ChunkRow(0, i % 5, T0 + 900 * i, "long", f"{i:032x}", 0) for i in range(300)]
    short = [ChunkRow(1, i, T0 + 100_000 + 10 * i, "short", f"{i:032x}", 0) for i in range(25)]
    reads = _Reads(long_run + short)
    q = ChangeQuery(T0, T0 + DAY, kind="upload", limit=1)
    assert [e.robot_id for e in reads.scan(q)] == ["short"] == [e.robot_id for e in reads.whole(q)]
