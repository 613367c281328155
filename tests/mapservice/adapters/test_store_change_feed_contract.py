"""The store contract, change feed role (`ChangeFeed`; the rule: mapservice/core/change_feed.py).

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py; shared helpers are in store_contract.py beside this module.
Times are taken from the wall clock (an hour ago, `t0`), because the ClickHouse tables drop
parts older than the retention.
"""

from __future__ import annotations

import pytest

from mapservice.core.wire2019 import content_hash

# --- the change feed (rule: mapservice/core/change_feed.py) -------------------------------


def _feed(store, t0, **kw):
    from mapservice.core.change_feed import ChangeQuery

    return store.change_feed(ChangeQuery(kw.pop("f", t0), kw.pop("t", t0 + 3_600_000), **kw))


def _upload(ev, robot: str, t0: int, n: int = 25, cols: int = 10) -> list:
    """A floor upload: n chunks by one writer, 100 ms apart."""
    return [
        ev.chunk(robot, t0 + 100 * i, i // cols, i % cols, bytes([i]) * 10_000) for i in range(n)
    ]


def test_change_feed_is_newest_first_with_previous_content(store, ev, t0) -> None:
    """Floor changes come newest first, each with the chunk's content before it (also from
    a write before the window); a map upload is one entry, never a floor change; a write
    that leaves a chunk as it was is none."""
    from mapservice.core.change_feed import UPLOAD_MIN_CHUNKS

    base = t0 - 1_200_000  # the upload: 20 minutes before the window's start
    store.append(_upload(ev, "uploader", base, UPLOAD_MIN_CHUNKS + 5))
    a, b, c = (bytes([200 + i]) * 10_000 for i in range(3))
    store.append(
        [
            ev.chunk("r1", t0 + 60_000, 0, 1, a),
            ev.chunk("r2", t0 + 120_000, 0, 1, b),
            ev.chunk("r1", t0 + 180_000, 2, 3, c),
            # The same content again: no change of the floor.
            ev.chunk("r3", t0 + 200_000, 0, 1, b),
            ev.chunk("r3", t0 + 201_000, 4, 4, bytes([44]) * 10_000),
        ]
    )
    entries = _feed(store, t0)
    assert [(e.kind, e.ts_ms - t0, e.row, e.column, e.robot_id) for e in entries] == [
        ("change", 201_000, 4, 4, "r3"),
        ("change", 180_000, 2, 3, "r1"),
        ("change", 120_000, 0, 1, "r2"),
        ("change", 60_000, 0, 1, "r1"),
    ]
    assert entries[0].previous_hash is None
    assert entries[1].content_hash == content_hash(c).hex()
    assert entries[1].previous_hash == content_hash(bytes([23]) * 10_000).hex()
    assert entries[2].previous_hash == content_hash(a).hex()
    assert entries[3].previous_hash == content_hash(bytes([1]) * 10_000).hex()
    uploads = _feed(store, t0, f=base)
    assert [
        (e.kind, e.robot_id, e.chunks, e.ts_ms - base, e.end_ms - base)
        for e in uploads
        if e.kind == "upload"
    ] == [("upload", "uploader", UPLOAD_MIN_CHUNKS + 5, 0, 100 * (UPLOAD_MIN_CHUNKS + 4))]
    assert sum(e.kind == "change" for e in uploads) == 4


def test_change_feed_filters_area_and_robot_and_pages(store, ev, t0) -> None:
    """A chunk box, a robot and a cursor narrow the feed; pages follow one another without
    gaps or repeats; a short burst (fewer writes than an upload) stays floor changes."""
    from mapservice.core.change_feed import ChangeCursor, ChunkBox

    store.append(
        [ev.chunk(f"r{i % 3}", t0 + 1000 * i, i % 4, i % 5, bytes([i]) * 10_000) for i in range(12)]
    )
    everything = _feed(store, t0)
    assert len(everything) == 12 and all(e.kind == "change" for e in everything)
    box = ChunkBox(0, 1, 0, 1)
    assert [(e.row, e.column) for e in _feed(store, t0, box=box)] == [
        (r, c) for r, c in ((e.row, e.column) for e in everything) if r <= 1 and c <= 1
    ]
    assert {e.robot_id for e in _feed(store, t0, robot_id="r1")} == {"r1"}
    assert len(_feed(store, t0, robot_id="r1")) == 4
    first = _feed(store, t0, limit=5)
    cursor = ChangeCursor(*first[-1].key())
    assert ChangeCursor.decode(cursor.encode()) == cursor
    second = _feed(store, t0, limit=5, before=cursor)
    third = _feed(store, t0, limit=5, before=ChangeCursor(*second[-1].key()))
    assert first + second + third == everything
    assert _feed(store, t0, f=t0 + 12_000) == []


def test_change_feed_upload_shows_in_an_area_it_touched(store, ev, t0) -> None:
    """An upload is listed for an area when any of its writes is in it, once."""
    from mapservice.core.change_feed import ChunkBox

    store.append(_upload(ev, "up", t0 + 1000, 30, cols=10))  # rows 0-2, columns 0-9
    assert [(e.kind, e.chunks) for e in _feed(store, t0, box=ChunkBox(2, 2, 5, 5))] == [
        ("upload", 30)
    ]
    assert _feed(store, t0, box=ChunkBox(5, 6, 0, 9)) == []


def test_change_feed_lists_one_kind_when_asked(store, ev, t0) -> None:
    """kind="upload" lists the uploads alone (the timeline's marks), kind="change" the floor
    changes alone; paging works within a kind."""
    from mapservice.core.change_feed import ChangeCursor

    store.append(_upload(ev, "up-a", t0 + 1000, 25) + _upload(ev, "up-b", t0 + 600_000, 22))
    store.append(
        [ev.chunk("r1", t0 + 300_000 + 1000 * i, 7, i, bytes([90 + i]) * 10_000) for i in range(3)]
    )
    assert [(e.kind, e.robot_id, e.chunks) for e in _feed(store, t0, kind="upload")] == [
        ("upload", "up-b", 22),
        ("upload", "up-a", 25),
    ]
    assert [(e.kind, e.column) for e in _feed(store, t0, kind="change")] == [
        ("change", 2),
        ("change", 1),
        ("change", 0),
    ]
    first = _feed(store, t0, kind="upload", limit=1)
    assert [
        e.robot_id for e in _feed(store, t0, kind="upload", before=ChangeCursor(*first[0].key()))
    ] == ["up-a"]


def test_change_feed_refuses_a_window_with_too_many_writes(store, ev, t0, monkeypatch) -> None:
    """More writes than the feed reads at once: WindowTooBusy, not minutes of work."""
    from mapservice.core import change_feed

    monkeypatch.setattr(change_feed, "MAX_WRITES", 5)
    store.append([ev.chunk("r1", t0 + 2000 * i, 0, i % 3, bytes([i]) * 10_000) for i in range(6)])
    with pytest.raises(change_feed.WindowTooBusy, match="shorter span"):
        _feed(store, t0)


def test_change_feed_finds_a_weeks_uploads_without_reading_every_write(
    store, ev, t0, monkeypatch
) -> None:
    """kind="upload" over a week answers though the week holds more writes than the feed
    reads at once (the timeline's 7 d marks): the uploads alone are read (found where one
    writer's writes bunch up: mapservice/core/upload_scan.py), the same on every store,
    with the map uploader's single write and the area and robot filters as the feed has them."""
    from mapservice.core import change_feed
    from mapservice.core.change_feed import UPLOADER_ID, ChunkBox, WindowTooBusy

    monkeypatch.setattr(change_feed, "MAX_WRITES", 100)
    week_from = t0 - 6 * 86_400_000
    # Robots' writes every 30 s (more than MAX_WRITES in all), two uploads, one map-upload write.
    store.append(
        [
            ev.chunk(
                f"r{i % 3}", t0 - 3_600_000 + 30_000 * i, i % 4, i % 5, bytes([i % 9]) * 10_000
            )
            for i in range(240)
        ]
    )
    store.append(_upload(ev, "up-a", t0 - 1_800_000 + 5, 25))
    store.append(
        [
            ev.chunk("r2", t0 + 605_000 + 900 * i, 5, i % 8, bytes([60 + i]) * 10_000)
            for i in range(21)
        ]
    )
    store.append([ev.chunk(UPLOADER_ID, t0 + 1_200_000 + 7, 6, 6, bytes([77]) * 10_000)])
    with pytest.raises(WindowTooBusy):
        _feed(store, t0, f=week_from)
    want = [
        ("upload", UPLOADER_ID, 1, 1_200_007, 1_200_007),
        ("upload", "r2", 21, 605_000, 605_000 + 900 * 20),
        ("upload", "up-a", 25, -1_799_995, -1_799_995 + 2_400),
    ]

    def uploads(**kw) -> list:
        return [
            (e.kind, e.robot_id, e.chunks, e.ts_ms - t0, e.end_ms - t0)
            for e in _feed(store, t0, f=week_from, kind="upload", **kw)
        ]

    # Before any snapshot, with the snapshots built (ClickHouse keeps the counts of the
    # buckets before them), and after a late upload's repair.
    assert uploads() == want
    store.build_snapshots(t0 + 1_000_000)
    assert uploads() == want
    assert uploads(robot_id="r2") == want[1:2]
    assert uploads(box=ChunkBox(5, 5, 7, 7)) == want[1:2]
    store.append(
        [ev.chunk("late", t0 + 1000 * i, 7, i % 5, bytes([120 + i]) * 10_000) for i in range(20)]
    )
    assert uploads() == [*want[:2], ("upload", "late", 20, 0, 19_000), want[2]]
    store.repair_snapshots()
    assert uploads() == [*want[:2], ("upload", "late", 20, 0, 19_000), want[2]]
