"""An in-memory HistoryStore with the same semantics as ClickHouse (for pure tests).

It keeps what ClickHouse keeps: positions to the millimetre, quaternions and battery as
32-bit floats, one row per natural identity (the last write wins).
"""

from __future__ import annotations

import datetime
import threading
from collections.abc import Sequence

import msgspec

from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
from mapservice.core import change_scan, upload_scan
from mapservice.core.annotations import (
    ANNOTATION_EVENTS,
    AnnotationEdit,
    CurrentAnnotation,
    ZoneViolation,
    fold_annotations,
    prune_before,
)
from mapservice.core.change_feed import UPLOADER_ID, ChangeEntry, ChangeQuery
from mapservice.core.commands import COMMAND_EVENTS, StoredCommandEvent
from mapservice.core.events import (
    ChunkUpdated,
    DeadLetter,
    Envelope,
    MapMetaSet,
)
from mapservice.core.heatmaps import (
    CountedIncidents,
    HeatmapCell,
    HeatmapRule,
    count_incidents,
    fold_heatmap,
)
from mapservice.core.incidents import Incident
from mapservice.core.legacy_query import ChunkQuery, PoseQuery, select
from mapservice.core.ports import (
    ChunkRow,
    ChunkState,
    ConflictRow,
    Counts,
    PoseRow,
    RetentionResult,
    TimelineBucket,
    TrackBucket,
)
from mapservice.core.retention import DAY_MS
from mapservice.core.stored_rows import pose_rows_of
from mapservice.core.timetravel import fold_map, fold_robots, timeline_buckets
from mapservice.core.track_buckets import fold_track_buckets
from mapservice.core.vda_facts import VdaConnectionRow, VdaFacts
from mapservice.core.webhook_registry import RegisteredWebhook, WebhookReport
from mapservice.testing.memory_incidents import IncidentLog
from mapservice.testing.memory_vda import VdaLog
from mapservice.testing.memory_webhooks import WebhookLog


def _iso_day(ms: int) -> str:
    return datetime.datetime.fromtimestamp(ms / 1000, datetime.UTC).date().isoformat()


class MemoryStore:
    def __init__(self, retention_days: int = 7, heatmap_rule: HeatmapRule | None = None) -> None:
        self.retention_days = retention_days
        self.heatmap_rule = heatmap_rule or HeatmapRule()
        # The floor carried across the retention boundary: per chunk, the winning write at
        # the last boundary applied (ClickHouse: the anchor snapshot's rows).
        self._carried: dict[tuple[int, int], ChunkState] = {}
        self._poses: dict[tuple[str, int], PoseRow] = {}
        self._chunks: dict[tuple[int, int, int, str], ChunkRow] = {}
        self._contents: dict[bytes, tuple[int, int, bytes]] = {}
        self._metas: dict[tuple[int, str], MapMetaSet] = {}
        self._dead: list[DeadLetter] = []
        self._conflicts: dict[tuple[int, int, int, str], ConflictRow] = {}
        self._vda = VdaLog()
        self._annotation_edits: dict[tuple[str, int, str], AnnotationEdit] = {}
        self._zone_violations: dict[tuple[int, str, str], ZoneViolation] = {}
        self._incidents = IncidentLog()
        self._webhooks = WebhookLog()  # state, not history: the retention keeps it
        self._commands: dict[tuple[int, str], StoredCommandEvent] = {}  # (time, event id)
        self._lock = threading.Lock()

    def migrate(self) -> int:
        return SCHEMA_VERSION

    def append(self, events: Sequence[Envelope]) -> None:
        self.append_events(events)
        self.derive_views(events)

    def derive_views(self, events: Sequence[Envelope]) -> None:
        """Nothing to do: this store's downsampled and timeline reads fold the poses."""

    def append_events(self, events: Sequence[Envelope]) -> None:
        with self._lock:
            for e in events:
                p = e.payload
                self._vda.append(e)
                if (row := next(iter(pose_rows_of((e,))), None)) is not None:
                    self._poses[(e.robot_id, e.event_time_ms)] = row
                elif isinstance(p, ChunkUpdated):
                    self._contents.setdefault(p.content_hash, (p.width, p.height, p.data))
                    key = (e.event_time_ms, p.row, p.column, e.robot_id)
                    self._chunks[key] = ChunkRow(
                        p.row,
                        p.column,
                        e.event_time_ms,
                        e.robot_id,
                        p.content_hash.hex(),
                        e.receive_time_ms,
                    )
                elif isinstance(p, MapMetaSet):
                    self._metas[(e.event_time_ms, e.robot_id)] = p
                elif isinstance(p, ANNOTATION_EVENTS):
                    self._annotation_edits[(p.annotation_id, e.event_time_ms, e.event_id)] = (
                        AnnotationEdit(e.event_time_ms, e.event_id, p)
                    )
                elif isinstance(p, COMMAND_EVENTS):
                    self._commands[(e.event_time_ms, e.event_id)] = StoredCommandEvent(
                        e.event_time_ms, e.event_id, p
                    )

    def command_events(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 10_000
    ) -> list[StoredCommandEvent]:
        with self._lock:
            return [
                self._commands[k]
                for k in sorted(self._commands)
                if from_ms <= k[0] < to_ms and robot_id in (None, self._commands[k].event.robot_id)
            ][:limit]

    def annotations_at(self, at_ms: int) -> list[CurrentAnnotation]:
        with self._lock:
            current = fold_annotations(list(self._annotation_edits.values()), at_ms)
        return [current[k] for k in sorted(current)]

    def append_zone_violations(self, rows: Sequence[ZoneViolation]) -> None:
        with self._lock:
            for v in rows:
                self._zone_violations[(v.ts_ms, v.robot_id, v.annotation_id)] = v

    def append_incidents(
        self, found: Sequence[Incident], found_ms: int, retracted: Sequence[Incident] = ()
    ) -> None:
        self._incidents.append(found, found_ms, retracted)

    def incidents(
        self,
        from_ms: int,
        to_ms: int,
        kinds: Sequence[str] = (),
        robot_id: str | None = None,
        limit: int = 10_000,
    ) -> list[Incident]:
        return self._incidents.incidents(from_ms, to_ms, kinds, robot_id, limit)

    def incidents_per_cell(
        self, from_ms: int, to_ms: int, factor: int, limit: int = 100_000
    ) -> CountedIncidents:
        if factor < 1:
            raise ValueError("factor must be positive")
        listed = self._incidents.incidents(from_ms, to_ms, limit=limit + 1)
        return count_incidents(listed, factor, limit)

    def save_webhook(self, webhook: RegisteredWebhook, changed_ms: int) -> None:
        self._webhooks.save_webhook(webhook, changed_ms)

    def remove_webhook(self, webhook_id: str, changed_ms: int) -> None:
        self._webhooks.remove_webhook(webhook_id, changed_ms)

    def webhooks(self) -> list[RegisteredWebhook]:
        return self._webhooks.webhooks()

    def report_webhooks(self, reports: Sequence[WebhookReport]) -> None:
        self._webhooks.report_webhooks(reports)

    def webhook_reports(self) -> list[WebhookReport]:
        return self._webhooks.webhook_reports()

    def zone_violations(
        self, from_ms: int, to_ms: int, limit: int = 100_000
    ) -> list[ZoneViolation]:
        with self._lock:
            return [
                self._zone_violations[k]
                for k in sorted(self._zone_violations)
                if from_ms <= k[0] < to_ms
            ][:limit]

    def annotation_edits(
        self, from_ms: int, to_ms: int, limit: int = 10_000
    ) -> list[AnnotationEdit]:
        with self._lock:
            edits = [e for e in self._annotation_edits.values() if from_ms <= e.ts_ms < to_ms]
        return sorted(edits, key=lambda e: (e.ts_ms, e.event_id))[:limit]

    def vda_facts(self, robot_id: str, from_ms: int, to_ms: int, limit: int = 10_000) -> VdaFacts:
        return self._vda.vda_facts(robot_id, from_ms, to_ms, limit)

    def connection_states_at(
        self, at_ms: int, since_ms: int, robots: Sequence[str]
    ) -> dict[str, VdaConnectionRow]:
        return self._vda.connection_states_at(at_ms, since_ms, robots)

    def vda_fleet_facts(self, from_ms: int, to_ms: int, limit: int = 10_000) -> dict[str, VdaFacts]:
        return self._vda.vda_fleet_facts(from_ms, to_ms, limit)

    def append_dead_letters(self, records: Sequence[DeadLetter]) -> None:
        with self._lock:
            self._dead.extend(records)

    def poses(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 100_000
    ) -> list[PoseRow]:
        rows = [
            r
            for r in self._poses.values()
            if from_ms <= r.ts_ms < to_ms and (robot_id is None or r.robot_id == robot_id)
        ]
        return sorted(rows, key=lambda r: (r.ts_ms, r.robot_id))[:limit]

    def poses_downsampled(
        self,
        from_ms: int,
        to_ms: int,
        step_ms: int,
        robot_id: str | None = None,
        limit: int = 100_000,
    ) -> list[PoseRow]:
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        first: dict[tuple[str, int], PoseRow] = {}
        for r in self.poses(from_ms, to_ms, robot_id, limit=len(self._poses)):
            first.setdefault((r.robot_id, (r.ts_ms - from_ms) // step_ms), r)
        return sorted(first.values(), key=lambda r: (r.ts_ms, r.robot_id))[:limit]

    def robot_track(
        self, robot_id: str, from_ms: int, to_ms: int, step_ms: int = 0, limit: int = 100_000
    ) -> list[PoseRow]:
        if step_ms < 0:
            raise ValueError("step_ms must not be negative")
        rows = (
            self.poses_downsampled(from_ms, to_ms, step_ms, robot_id, limit)
            if step_ms
            else self.poses(from_ms, to_ms, robot_id, limit)
        )
        return [msgspec.structs.replace(r, path=None) for r in rows]

    def track_buckets(
        self, robot_id: str, from_ms: int, to_ms: int, bucket_ms: int
    ) -> list[TrackBucket]:
        rows = self.poses(from_ms, to_ms, robot_id, limit=len(self._poses))
        return fold_track_buckets(rows, from_ms, to_ms, bucket_ms)

    def heatmap_cells(
        self, from_ms: int, to_ms: int, factor: int, limit: int = 1_000_000
    ) -> list[HeatmapCell]:
        if factor < 1:
            raise ValueError("factor must be positive")
        start = from_ms - from_ms % 1000 - self.heatmap_rule.lookback_ms
        rows = self.poses(start, to_ms, None, limit=len(self._poses))
        return fold_heatmap(rows, from_ms, to_ms, factor, self.heatmap_rule)[:limit]

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        rows = [r for r in self._chunks.values() if from_ms <= r.ts_ms < to_ms]
        return sorted(rows, key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))[:limit]

    def chunk_events_compacted(
        self, from_ms: int, to_ms: int, step_ms: int, limit: int = 100_000
    ) -> list[ChunkRow]:
        if step_ms <= 0:
            raise ValueError("step_ms must be positive")
        won: dict[tuple[int, int, int], ChunkRow] = {}
        for r in self.chunk_events(from_ms, to_ms, limit=len(self._chunks)):
            k = (r.row, r.column, r.ts_ms // step_ms)
            if k not in won or (r.ts_ms, r.robot_id) > (won[k].ts_ms, won[k].robot_id):
                won[k] = r
        return sorted(won.values(), key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))[:limit]

    def timeline(self, from_ms: int, to_ms: int, buckets: int) -> list[TimelineBucket]:
        bucket_ms, starts = timeline_buckets(from_ms, to_ms, buckets)
        chunks = [0] * len(starts)
        robots: list[set[str]] = [set() for _ in starts]
        for c in self._chunks.values():
            if from_ms <= c.ts_ms < to_ms:
                chunks[(c.ts_ms - from_ms) // bucket_ms] += 1
        for p in self._poses.values():
            if from_ms <= p.ts_ms < to_ms:
                robots[(p.ts_ms - from_ms) // bucket_ms].add(p.robot_id)
        conflicts = self.conflict_counts(from_ms, to_ms, bucket_ms) if starts else {}
        return [
            TimelineBucket(start, chunks[k], conflicts.get(start, 0), len(robots[k]))
            for k, start in enumerate(starts)
        ]

    def robot_known(self, robot_id: str) -> bool:
        return any(r == robot_id for r, _ in self._poses)

    def map_at(self, at_ms: int) -> list[ChunkState]:
        state = fold_map([*self._carried.values(), *self._chunks.values()], at_ms)
        return [state[k] for k in sorted(state)]

    def robots_at(
        self, at_ms: int, after: str | None = None, limit: int | None = None
    ) -> list[PoseRow]:
        state = fold_robots(list(self._poses.values()), at_ms)
        page = [state[k] for k in sorted(state) if after is None or k > after]
        return page if limit is None else page[:limit]

    def build_snapshots(self, up_to_ms: int) -> int:
        return 0  # folds the whole history on every read: nothing to snapshot

    def repair_snapshots(self, max_snapshots: int = 144) -> int:
        return 0  # no snapshots, nothing a late event could invalidate

    def apply_retention(self, now_ms: int) -> RetentionResult:
        """As ClickHouse's retention step, with the boundary itself as the anchor: the
        floor at the boundary is carried, the days before the boundary's day go, contents
        stay while a kept write or the carried floor names them, and so does each robot's
        last pose at the boundary."""
        boundary = now_ms - self.retention_days * DAY_MS
        cut = boundary // DAY_MS * DAY_MS
        with self._lock:
            self._annotation_edits = {
                (e.event.annotation_id, e.ts_ms, e.event_id): e
                for e in prune_before(self._annotation_edits.values(), boundary)
            }
            carried_poses = {
                (p.robot_id, p.ts_ms)
                for p in fold_robots(list(self._poses.values()), boundary).values()
            }
            self._commands = {k: v for k, v in self._commands.items() if k[0] >= cut}
            self._vda.drop_before(cut)
            old_chunks = [k for k in self._chunks if k[0] < cut]
            old_poses = [k for k in self._poses if k[1] < cut and k not in carried_poses]
            if not old_chunks and not old_poses:
                return RetentionResult(boundary, _iso_day(cut), 0, 0)
            dropped_days = {k[0] // DAY_MS for k in old_chunks} | {
                k[1] // DAY_MS for k in old_poses
            }
            self._carried = fold_map([*self._carried.values(), *self._chunks.values()], boundary)
            for k in old_chunks:
                del self._chunks[k]
            for key in old_poses:
                del self._poses[key]
            self._conflicts = {k: v for k, v in self._conflicts.items() if k[0] >= cut}
            self._zone_violations = {k: v for k, v in self._zone_violations.items() if k[0] >= cut}
            self._incidents.forget_before(cut)
            self._dead = [d for d in self._dead if d.receive_time_ms >= cut]
            named = {bytes.fromhex(c.content_hash) for c in self._carried.values()} | {
                bytes.fromhex(c.content_hash) for c in self._chunks.values()
            }
            self._contents = {h: v for h, v in self._contents.items() if h in named}
            in_force = [k for k in self._metas if k[0] <= boundary]
            if in_force:
                keep = max(in_force)
                self._metas = {k: v for k, v in self._metas.items() if k >= keep}
            return RetentionResult(boundary, _iso_day(cut), len(dropped_days), 0)

    def chunk_writes_near(
        self, chunks: Sequence[tuple[int, int]], from_ms: int, to_ms: int
    ) -> list[ChunkRow]:
        wanted = set(chunks)
        rows = [
            r
            for r in self._chunks.values()
            if from_ms <= r.ts_ms <= to_ms and (r.row, r.column) in wanted
        ]
        return sorted(rows, key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id))

    def append_conflicts(self, rows: Sequence[ConflictRow]) -> None:
        with self._lock:
            for c in rows:
                key = (c.ts_ms, c.row, c.column, c.robot_b)
                current = self._conflicts.get(key)
                # As ReplacingMergeTree(ts_a): the row naming the later A wins.
                if current is None or c.ts_a_ms >= current.ts_a_ms:
                    self._conflicts[key] = c

    def conflicts(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ConflictRow]:
        return [self._conflicts[k] for k in sorted(self._conflicts) if from_ms <= k[0] < to_ms][
            :limit
        ]

    def conflict_counts(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        if bucket_ms <= 0:
            raise ValueError("bucket_ms must be positive")
        counts: dict[int, int] = {}
        for ts in (k[0] for k in self._conflicts if from_ms <= k[0] < to_ms):
            start = from_ms + (ts - from_ms) // bucket_ms * bucket_ms
            counts[start] = counts.get(start, 0) + 1
        return dict(sorted(counts.items()))

    def change_feed(self, query: ChangeQuery) -> list[ChangeEntry]:
        if query.kind == "upload":
            return upload_scan.newest_first(query, self._write_bursts, self._chunk_writes)
        return change_scan.newest_first(query, self._chunk_writes, self._hashes_before)

    def _write_bursts(self, from_ms: int, to_ms: int, robot: str | None) -> list[tuple[str, int]]:
        counts: dict[tuple[str, int], int] = {}
        for r in self._chunks.values():
            if from_ms <= r.ts_ms < to_ms and (robot is None or r.robot_id == robot):
                k = (
                    r.robot_id,
                    r.ts_ms // upload_scan.BURST_BUCKET_MS * upload_scan.BURST_BUCKET_MS,
                )
                counts[k] = counts.get(k, 0) + 1
        return [
            k for k, n in counts.items() if n >= upload_scan.BURST_MIN_WRITES or k[0] == UPLOADER_ID
        ]

    def _chunk_writes(self, from_ms: int, to_ms: int, robots=None) -> list[ChunkRow]:
        return sorted(
            (
                r
                for r in self._chunks.values()
                if from_ms <= r.ts_ms < to_ms and (robots is None or r.robot_id in robots)
            ),
            key=lambda r: (r.ts_ms, r.row, r.column, r.robot_id),
        )

    def _hashes_before(
        self, wanted: set[tuple[int, int]], before_ms: int
    ) -> dict[tuple[int, int], str]:
        earlier: dict[tuple[int, int], tuple[int, str, str]] = {}
        # The floor the retention carried (writes from days it dropped) and the kept writes.
        kept: list[ChunkState | ChunkRow] = [*self._carried.values(), *self._chunks.values()]
        for r in kept:
            k = (r.row, r.column)
            if (
                r.ts_ms < before_ms
                and k in wanted
                and (r.ts_ms, r.robot_id) > earlier.get(k, (-1, "", ""))[:2]
            ):
                earlier[k] = (r.ts_ms, r.robot_id, r.content_hash)
        return {k: v[2] for k, v in earlier.items()}

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        return self._contents.get(content_hash)

    def chunk_contents(self, hashes: Sequence[bytes]) -> dict[bytes, tuple[int, int, bytes]]:
        return {h: self._contents[h] for h in set(hashes) if h in self._contents}

    def latest_meta(self) -> MapMetaSet | None:
        if not self._metas:
            return None
        return self._metas[max(self._metas)]

    def list_chunks(self, query: ChunkQuery) -> list[ChunkRow]:
        return select(list(self._chunks.values()), query)

    def list_poses(self, query: PoseQuery) -> list[PoseRow]:
        return select(list(self._poses.values()), query)

    def delete_chunks(self) -> int:
        with self._lock:
            removed = len(self._chunks)
            self._chunks.clear()
            self._carried.clear()  # as ClickHouse truncates its snapshots
            self._conflicts.clear()  # derived from the writes just deleted
        return removed

    def delete_meta(self) -> int:
        with self._lock:
            removed = len(self._metas)
            self._metas.clear()
        return removed

    def counts(self) -> Counts:
        return Counts(len(self._poses), len(self._chunks), len(self._contents), len(self._dead))

    def close(self) -> None:
        pass
