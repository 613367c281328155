"""Retention that keeps state, for every HistoryStore: 25 simulated days of floor changes,
robots, conflicts, late writes and store restarts on a ManualClock, with a retention of 7
days applied along the way (three retention periods and more), checked at many instants
against a brute-force fold of everything ever written.

The floor is written once on day 0 and most of it never changes (walls), so every check
after day 8 asks for state that only the carried snapshot and the renewed contents hold.
"""

from __future__ import annotations

import base64
import datetime as dt
import itertools
import zlib

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationEdit,
    AnnotationRemoved,
    PointOfInterest,
    Zone,
    fold_annotations,
)
from mapservice.core.change_feed import ChangeQuery
from mapservice.core.events import make_envelope
from mapservice.core.ports import ConflictRow
from mapservice.core.timetravel import fold_map, fold_robots
from mapservice.core.wire2019 import content_hash, format_timestamp
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event, clone_migrated, meta_event, pose_event

DAY = 86_400_000
HOUR = 3_600_000
STEP = 6 * HOUR
RETENTION_DAYS = 7
DAYS = 25
# A fixed start long before the wall clock's retention: only the service's clock decides.
T0 = int(dt.datetime(2026, 1, 1, tzinfo=dt.UTC).timestamp() * 1000)
ROWS, COLS = 4, 5
ROBOTS = ("amr-1", "amr-2", "amr-3")

_databases = itertools.count()


def _pixels(row: int, col: int, version: int) -> bytes:
    return bytes([(row * 31 + col * 7 + version * 13) % 256]) * 100 + bytes(range(100)) * 99


class Store:
    """A store of one kind that can be restarted (a new store object on the same data)."""

    def __init__(self, kind: str, chdb_dir) -> None:
        self.kind, self.chdb_dir = kind, chdb_dir
        self.database = f"retention_{next(_databases)}"
        self.store = self._open()
        if kind != "memory":  # the module's migrated template, copied (the retention is its 7 days)
            clone_migrated(chdb_dir, self.database)
        self.store.migrate()

    def _open(self):
        if self.kind == "memory":
            return MemoryStore(retention_days=RETENTION_DAYS)
        return ClickHouseStore(
            f"chdb://{self.chdb_dir}",
            database=self.database,
            retention_days=RETENTION_DAYS,
            snapshot_every_ms=STEP,
        )

    def restart(self) -> None:
        if self.kind == "memory":
            return  # its state is the object: nothing to reopen
        self.store.close()
        self.store = self._open()
        self.store.migrate()


class World:
    """Everything ever written, and the brute-force answers."""

    def __init__(self) -> None:
        self.chunks: list[_Row] = []  # every chunk write, as fold_map reads them
        self.pixels: dict[str, bytes] = {}
        self.poses = []
        self.conflicts: list[ConflictRow] = []
        self.versions = {(r, c): 0 for r in range(ROWS) for c in range(COLS)}
        self.annotation_edits: list[AnnotationEdit] = []

    def annotate(self, t: int, event):
        e = make_envelope("operator:t", t, t, event)
        self.annotation_edits.append(AnnotationEdit(t, e.event_id, event))
        return e

    def annotations_at(self, t: int) -> dict:
        return fold_annotations(self.annotation_edits, t)

    def chunk(self, robot: str, t: int, row: int, col: int):
        raw = _pixels(row, col, self.versions[(row, col)])
        e = chunk_event(robot, t, row, col, raw)
        self.chunks.append(_Row(row, col, t, robot, content_hash(raw).hex()))
        self.pixels[content_hash(raw).hex()] = raw
        return e

    def map_at(self, t: int) -> dict:
        return {
            k: (v.ts_ms, v.robot_id, v.content_hash) for k, v in fold_map(self.chunks, t).items()
        }

    def robots_at(self, t: int) -> dict:
        return {r: p.ts_ms for r, p in fold_robots(self.poses, t).items()}


class _Row:
    __slots__ = ("column", "content_hash", "robot_id", "row", "ts_ms")

    def __init__(self, row, column, ts_ms, robot_id, content_hash) -> None:
        self.row, self.column, self.ts_ms, self.robot_id, self.content_hash = (
            row,
            column,
            ts_ms,
            robot_id,
            content_hash,
        )


def _write_step(store, world: World, start: int, step_no: int) -> None:
    """Six hours: each robot reports every 30 min; a pallet moves (one chunk rewritten);
    sometimes two robots write one chunk within a minute (a conflict); sometimes a late
    write two days back (a snapshot repair)."""
    events = []
    for k in range(12):
        for i, robot in enumerate(ROBOTS):
            t = start + k * 1_800_000 + i * 1000
            events.append(pose_event(robot, t, x=float(step_no), y=float(k)))
            world.poses.append(_Pose(robot, t))
    row, col = 1 + step_no % 2, 1 + step_no % 3  # the aisles change; the walls never do
    world.versions[(row, col)] += 1
    t = start + 3 * HOUR + 17
    events.append(world.chunk(ROBOTS[step_no % 3], t, row, col))
    if step_no % 5 == 0:
        world.versions[(row, col)] += 1
        events.append(world.chunk(ROBOTS[(step_no + 1) % 3], t + 20_000, row, col))
        conflict = ConflictRow(
            row, col, t + 20_000, ROBOTS[step_no % 3], t, ROBOTS[(step_no + 1) % 3]
        )
        world.conflicts.append(conflict)
        store.append_conflicts([conflict])
    # The operators' week: zones and points of interest drawn in the first days, some
    # changed or removed later; most never touched again (the floor's state).
    if step_no < 7 * 4 and step_no % 3 == 0:
        n = step_no // 3
        shape = (
            Zone(f"zone {n}", "keep_out", ((n, 0.0), (n + 1.0, 0.0), (n + 1.0, 1.0)))
            if n % 2
            else PointOfInterest(f"poi {n}", "station", float(n), 2.0)
        )
        events.append(
            world.annotate(start + HOUR + n, AnnotationCreated(f"a{n}", "operator:t", shape))
        )
    if step_no % 11 == 5:
        n = (step_no // 11) % 9
        if f"a{n}" in world.annotations_at(start + 2 * HOUR):
            shape = PointOfInterest(f"poi {n} moved at {step_no}", "door", float(step_no), 1.0)
            events.append(
                world.annotate(start + 2 * HOUR, AnnotationChanged(f"a{n}", "operator:t", shape))
            )
    if step_no in (13, 40):
        removed = {13: "a4", 40: "a9"}[step_no]
        events.append(
            world.annotate(start + 2 * HOUR + 1, AnnotationRemoved(removed, "operator:t"))
        )
    if step_no % 7 == 3 and start - 2 * DAY > T0:
        late_row, late_col = 2, 4
        world.versions[(late_row, late_col)] += 1
        events.append(world.chunk("late-bot", start - 2 * DAY + 123, late_row, late_col))
    store.append(events)


class _Pose:
    __slots__ = ("robot_id", "ts_ms")

    def __init__(self, robot_id, ts_ms) -> None:
        self.robot_id, self.ts_ms = robot_id, ts_ms


def _check(store, world: World, now: int, client: TestClient) -> None:
    lo = now - RETENTION_DAYS * DAY
    instants = [lo, lo + 1, lo + DAY // 3, now - 3 * DAY - 7, now - DAY, now - HOUR, now]
    for t in instants:
        got = {(c.row, c.column): (c.ts_ms, c.robot_id, c.content_hash) for c in store.map_at(t)}
        want = world.map_at(t)
        assert got == want, (
            f"map at {format_timestamp(t)} (now {format_timestamp(now)}): "
            f"{len(got)} of {len(want)} chunks, {sum(got.get(k) == v for k, v in want.items())} right"
        )
        contents = store.chunk_contents([bytes.fromhex(h) for _, _, h in want.values()])
        for _, _, h in want.values():
            assert bytes.fromhex(h) in contents, f"pixels of {h} missing at {format_timestamp(t)}"
            assert zlib.decompress(contents[bytes.fromhex(h)][2]) == world.pixels[h]
        robots = {p.robot_id: p.ts_ms for p in store.robots_at(t)}
        assert robots == world.robots_at(t), f"robots at {format_timestamp(t)}"
        annotations = {a.annotation_id: a for a in store.annotations_at(t)}
        assert annotations == world.annotations_at(t), f"annotations at {format_timestamp(t)}"
    # The 2019 listing a robot downloads: latest=true&updatedBefore=T, with pixels.
    for t in (lo + 1, now - DAY):
        body = client.get(
            "/api/chunk-service/chunks",
            params={"latest": "true", "updatedBefore": str(t), "limit": "1000"},
        ).json()
        want = world.map_at(t - 1)
        assert len(body) == len(want), f"2019 latest listing before {format_timestamp(t)}"
        for doc in body:
            _, _, h = want[(doc["row"], doc["column"])]
            assert doc["chunk"] is not None, (
                f"2019 listing: chunk {doc['row']},{doc['column']} has no pixels"
            )
            assert zlib.decompress(base64.b64decode(doc["chunk"])) == world.pixels[h]
    # Timeline and conflicts over the whole retention, against the brute force.
    buckets = RETENTION_DAYS * 4
    timeline = store.timeline(lo, now, buckets)
    span = -(-(now - lo) // buckets)
    want_changes = [0] * buckets
    for c in world.chunks:
        if lo <= c.ts_ms < now:
            want_changes[(c.ts_ms - lo) // span] += 1
    want_conflicts = [0] * buckets
    for c in world.conflicts:
        if lo <= c.ts_ms < now:
            want_conflicts[(c.ts_ms - lo) // span] += 1
    assert [b.chunk_changes for b in timeline] == want_changes
    assert [b.conflicts for b in timeline] == want_conflicts
    want_robots: list[set] = [set() for _ in range(buckets)]
    for p in world.poses:
        if lo <= p.ts_ms < now:
            want_robots[(p.ts_ms - lo) // span].add(p.robot_id)
    assert [b.robots_active for b in timeline] == [len(r) for r in want_robots]
    assert store.conflicts(lo, now) == sorted(
        (c for c in world.conflicts if lo <= c.ts_ms < now),
        key=lambda c: (c.ts_ms, c.row, c.column, c.robot_b),
    )
    # The change feed of the whole retention, each change with the chunk's content before
    # it: for a chunk's first change in the retention, what a write now expired put there.
    # (The mapper's floor on day 0 is an upload, one entry of its own.)
    want_feed, content = [], {}
    for c in sorted(world.chunks, key=lambda c: (c.ts_ms, c.robot_id)):
        before = content.get((c.row, c.column))
        if lo <= c.ts_ms < now and before != c.content_hash and c.robot_id != "mapper":
            want_feed.append((c.ts_ms, c.row, c.column, c.robot_id, c.content_hash, before))
        content[(c.row, c.column)] = c.content_hash
    feed = store.change_feed(ChangeQuery(lo, now, limit=10_000, kind="change"))
    got_feed = sorted(
        (e.ts_ms, e.row, e.column, e.robot_id, e.content_hash, e.previous_hash) for e in feed
    )
    assert got_feed == sorted(want_feed), (
        f"change feed at {format_timestamp(now)}: "
        f"{[g for g in got_feed if g not in want_feed][:3]} instead of {[w for w in want_feed if w not in got_feed][:3]}"
    )


def _unnamed_snapshot_pixels(store: ClickHouseStore) -> int:
    db = store.database
    return store.rows(
        f"SELECT count() FROM {db}.map_snapshots WHERE content_hash NOT IN "
        f"(SELECT content_hash FROM {db}.chunk_contents)",
        {},
    )[0][0]


@pytest.mark.parametrize("kind", ["memory", "clickhouse"])
def test_three_retention_periods_keep_the_floor_exact(kind, request) -> None:
    # The memory twin needs no chDB: the module's engine (a migrated template) only for ClickHouse.
    s = Store(kind, None if kind == "memory" else request.getfixturevalue("chdb_dir"))
    clock = ManualClock(T0)
    world = World()
    # Day 0: the map meta and the whole floor, written once.
    s.store.append([meta_event(T0, chunk_rows=ROWS, chunk_cols=COLS)])
    s.store.append(
        [
            world.chunk("mapper", T0 + 1000 + r * COLS + c, r, c)
            for r in range(ROWS)
            for c in range(COLS)
        ]
    )
    bytes_per_day: dict[int, int] = {}
    steps_per_day = DAY // STEP
    for step_no in range(DAYS * steps_per_day):
        _write_step(s.store, world, T0 + step_no * STEP, step_no)
        clock.advance(STEP)
        now = clock.now_ms()
        while s.store.repair_snapshots():
            pass
        s.store.build_snapshots(now - 60_000)
        s.store.apply_retention(now)
        if (step_no + 1) % steps_per_day:
            continue
        day = (step_no + 1) // steps_per_day
        if day % 4 == 0:
            s.restart()
        client = TestClient(create_app(Settings(retention_days=RETENTION_DAYS), s.store, {}, clock))
        _check(s.store, world, now, client)
        assert s.store.latest_meta().chunk_rows == ROWS
        if day >= 8:
            # The week's annotations outlive every retention period; their edits older
            # than the retention are gone but for those the standing ones are folded from.
            standing = world.annotations_at(now)
            assert {"a0", "a1", "a2", "a3"} <= set(standing) and "a4" not in standing
            assert ("a9" in standing) == (day <= 10)  # removed on day 10
            boundary = now - RETENTION_DAYS * DAY
            at_boundary = world.annotations_at(boundary)
            old = [e for e in s.store.annotation_edits(T0, now + 1, 100_000) if e.ts_ms < boundary]
            assert all(e.event.annotation_id in at_boundary for e in old)
            assert len(old) <= 2 * len(at_boundary)
        if kind == "clickhouse":
            assert _unnamed_snapshot_pixels(s.store) == 0, (
                f"day {day}: a snapshot names missing pixels"
            )
            s.store.optimize()
            bytes_per_day[day] = sum(s.store.storage_bytes().values())
            carried = s.store.rows(f"SELECT count() FROM {s.database}.carried_poses", {})[0][0]
            assert carried <= len(ROBOTS), "carried_poses holds more than a pose per robot"
    if kind == "clickhouse":
        # Flat after the first retention period: what the last day holds is what day 9 held
        # (the kept week and the renewed floor), give or take a part's compression.
        steady = [bytes_per_day[d] for d in range(RETENTION_DAYS + 2, DAYS + 1)]
        assert max(steady) < 1.2 * min(steady), bytes_per_day
        print("bytes on disk per simulated day:", bytes_per_day)
    s.store.close()
