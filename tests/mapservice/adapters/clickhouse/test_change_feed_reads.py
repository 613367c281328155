"""The ClickHouse change feed's previous contents come from the nearest valid map snapshot
plus the writes after it (not every write before the slice), and equal the memory fold:
with a snapshot, with writes after it, and with the snapshot made invalid by a late write."""

from __future__ import annotations

import time

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.core.change_feed import ChangeQuery
from mapservice.core.wire2019 import content_hash
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event


def test_previous_contents_from_the_snapshot_and_the_writes_after_it(tmp_path) -> None:
    hour_ago = int(time.time() * 1000) - 3_600_000
    t0 = hour_ago - hour_ago % 600_000
    a, b, c, d = (bytes([i]) * 10_000 for i in (11, 22, 33, 44))
    before = [
        chunk_event("r1", t0 - 1_500_000, 0, 0, a),
        chunk_event("r2", t0 - 1_400_000, 0, 1, a),
        chunk_event("r1", t0 - 1_300_000, 0, 2, a),
    ]
    after_snapshot = [chunk_event("r2", t0 - 300_000, 0, 1, b)]
    window = [chunk_event("r3", t0 + 60_000 + i * 5_000, 0, i, c) for i in range(3)]
    memory = MemoryStore()
    store = ClickHouseStore(f"chdb://{tmp_path / 'ch'}", database="feed")
    try:
        store.migrate()
        for s in (memory, store):
            s.append(before)
        store.build_snapshots(t0 - 1_200_000)
        for s in (memory, store):
            s.append(after_snapshot + window)
        q = ChangeQuery(t0, t0 + 600_000)
        entries = store.change_feed(q)
        assert entries == memory.change_feed(q)
        assert [(e.column, e.previous_hash) for e in entries] == [
            (2, content_hash(a).hex()),
            (1, content_hash(b).hex()),
            (0, content_hash(a).hex()),
        ]
        # A late write before the snapshot invalidates it: the fold skips it, still exact.
        late = [chunk_event("r4", t0 - 1_250_000, 0, 2, d)]
        for s in (memory, store):
            s.append(late)
        entries = store.change_feed(q)
        assert entries == memory.change_feed(q)
        assert entries[0].previous_hash == content_hash(d).hex()
    finally:
        store.close()


def test_uploads_before_the_snapshot_are_found_from_chunk_bursts(tmp_path) -> None:
    """The snapshot builds keep, per writer and 20 s, the counts that may be an upload
    (chunk_bursts); the upload scan reads them before the newest valid snapshot instead of
    counting chunk_events there: a bucket missing from them is not found, one there is."""
    from mapservice.core.change_feed import UPLOADER_ID

    hour_ago = int(time.time() * 1000) - 3_600_000
    t0 = hour_ago - hour_ago % 600_000
    upload = [chunk_event("up", t0 + 100 * i, 0, i % 5, bytes([i]) * 10_000) for i in range(25)]
    alone = [chunk_event("r1", t0 + 60_000 * i, 1, 1, bytes([50 + i]) * 10_000) for i in range(9)]
    floor = [chunk_event(UPLOADER_ID, t0 + 300_007, 2, 2, bytes([99]) * 10_000)]
    store = ClickHouseStore(
        f"chdb://{tmp_path / 'ch'}", database="bursts", snapshot_every_ms=600_000
    )
    try:
        store.migrate()
        store.append(upload + alone + floor)
        store.build_snapshots(t0 + 600_000)
        kept = store.client.query(
            "SELECT toUnixTimestamp64Milli(toDateTime64(bucket, 3)), robot_id, writes "
            "FROM bursts.chunk_bursts FINAL ORDER BY ALL"
        ).result_rows
        assert kept == [(t0, "up", 25), (t0 + 300_000, UPLOADER_ID, 1)]
        q = ChangeQuery(t0 - 600_000, t0 + 600_000, kind="upload")
        assert [(e.robot_id, e.chunks) for e in store.change_feed(q)] == [
            (UPLOADER_ID, 1),
            ("up", 25),
        ]
        store.client.command("TRUNCATE TABLE bursts.chunk_bursts")
        assert store.change_feed(q) == []  # read from chunk_bursts, not counted again
    finally:
        store.close()
