"""The ports: small interfaces the components depend on. Adapters live in `adapters/`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

import msgspec

from mapservice.core.annotations import AnnotationEdit, CurrentAnnotation, ZoneViolation
from mapservice.core.bucket_rows import TimelineBucket as TimelineBucket
from mapservice.core.bucket_rows import TrackBucket as TrackBucket
from mapservice.core.commands import StoredCommandEvent
from mapservice.core.events import ChunkUpdated, DeadLetter, Envelope, MapMetaSet
from mapservice.core.incident_ports import IncidentFeed as IncidentFeed
from mapservice.core.vda_facts import VdaConnectionRow as VdaConnectionRow
from mapservice.core.vda_facts import VdaErrorRow as VdaErrorRow
from mapservice.core.vda_facts import VdaFacts as VdaFacts
from mapservice.core.vda_facts import VdaFactsheetRow as VdaFactsheetRow

if TYPE_CHECKING:
    from mapservice.core.change_feed import ChangeEntry, ChangeQuery
    from mapservice.core.heatmaps import CountedIncidents, HeatmapCell
    from mapservice.core.incident_model import Incident
    from mapservice.core.legacy_query import ChunkQuery, PoseQuery
    from mapservice.core.webhook_registry import RegisteredWebhook, WebhookReport


class Clock(Protocol):
    def now_ms(self) -> int:
        """Milliseconds since the epoch, UTC."""


class EventPublisher(Protocol):
    """Appends records to a durable log; `on_done(error)` fires once the log has them."""

    def publish(
        self, topic: str, key: bytes, value: bytes, on_done: Callable[[Exception | None], None]
    ) -> None: ...

    def poll(self, timeout: float) -> None:
        """Runs pending delivery callbacks."""

    def flush(self, timeout: float) -> int:
        """Waits for outstanding records; returns how many are still undelivered."""


class LiveFeed(Protocol):
    """Where stored batches go for live viewers (mapservice/core/live_messages.py); never blocks."""

    def publish(self, events: Sequence[Envelope]) -> None:
        """Called after `events` are in the history, so queryable."""


# The records are frozen and hold only immutable values, so none can be part of a reference
# cycle: `gc=False` keeps them out of the cyclic collector (mapservice/runtime/heap.py).
class PoseRow(msgspec.Struct, frozen=True, gc=False, array_like=True):
    robot_id: str
    ts_ms: int
    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float
    battery_level: float | None
    charging: bool | str | None
    loaded: bool | str | None
    path: tuple[tuple[float, float], ...] | None
    receive_time_ms: int


class ChunkRow(msgspec.Struct, frozen=True, gc=False, array_like=True):
    row: int
    column: int
    ts_ms: int
    robot_id: str
    content_hash: str  # hex
    receive_time_ms: int


def chunk_rows_of(events: Sequence[Envelope]) -> list[ChunkRow]:
    """The chunk writes among `events`, as the store lists them (which write, not its pixels)."""
    return [
        ChunkRow(
            e.payload.row,
            e.payload.column,
            e.event_time_ms,
            e.robot_id,
            e.payload.content_hash.hex(),
            e.receive_time_ms,
        )
        for e in events
        if isinstance(e.payload, ChunkUpdated)
    ]


class ChunkState(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """A chunk's current version in a map at an instant: which write, not its pixels."""

    row: int
    column: int
    ts_ms: int
    robot_id: str
    content_hash: str  # hex


class SourceRecord(msgspec.Struct, frozen=True, gc=False):
    topic: str
    partition: int
    offset: int
    value: bytes
    # Which of the source's memberships in its consumer group delivered it. A source whose
    # partitions can move (Kafka) counts them and never commits a past one's records.
    membership: int = 0


class EventSource(Protocol):
    """Reads a durable log in batches; nothing counts as consumed until `commit`."""

    def start(self) -> None: ...

    def poll(self, max_records: int, timeout_s: float) -> list[SourceRecord]:
        """Up to `max_records` records, waiting at most `timeout_s` for the first."""

    def commit(self, records: Sequence[SourceRecord]) -> bool:
        """Marks the records consumed; False when they will be delivered again instead
        (a source that commits asynchronously may also learn that only later)."""

    def stay_in_group(self) -> None:
        """Called every few seconds while the consumer works long between polls (a views
        rebuild, inserts retried through an outage): keeps its membership without handing
        out records, which the next poll delivers in order. A group change meanwhile is
        taken as in a poll."""

    def close(self) -> None: ...


class Counts(msgspec.Struct, frozen=True, gc=False):
    poses: int
    chunk_events: int
    chunk_contents: int
    dead_letters: int


class ConflictRow(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """Two robots wrote different content to one chunk within the conflict window:
    `robot_a` at `ts_a_ms` first, `robot_b` at `ts_ms` (the later write's event time).
    Both writes, with their contents, are in the chunk history under these identities."""

    row: int
    column: int
    ts_ms: int
    robot_a: str
    ts_a_ms: int
    robot_b: str


class RetentionResult(msgspec.Struct, frozen=True):
    """What one retention step did: the snapshot instant that carries the floor across the
    boundary (None: none yet, nothing dropped), the first day kept (ISO date), the day
    partitions dropped and the chunk contents renewed (pixels a retained row still names)."""

    anchor_ms: int | None
    first_day_kept: str | None
    partitions_dropped: int
    contents_renewed: int


class ChangeFeed(Protocol):
    """The map's changes page by page (mapservice/core/change_feed.py has the rule)."""

    def change_feed(self, query: ChangeQuery) -> list[ChangeEntry]:
        """The query's page: floor changes and map uploads (one entry each), newest first."""


class StoreSchema(Protocol):
    """The store's schema (ClickHouse: `migrations`)."""

    def migrate(self) -> int:
        """Creates or upgrades the schema; returns the schema version. Safe to repeat."""


class HistoryWriter(Protocol):
    """Appends to the history, idempotent on each event's natural identity (ClickHouse:
    `writes`). The processors' history sink, the conflict recorder and the backfill write here."""

    def append(self, events: Sequence[Envelope]) -> None:
        """Stores `events`: `append_events`, then `derive_views`."""

    def append_events(self, events: Sequence[Envelope]) -> None:
        """Stores `events` where the event reads (poses, chunk events, map meta) find them;
        the derived pose views may lag until `derive_views` of the same events."""

    def derive_views(self, events: Sequence[Envelope]) -> None:
        """Brings the derived pose views (downsampled replay, timeline) up to `events`,
        already stored by `append_events`; repeating it changes nothing."""

    def append_dead_letters(self, records: Sequence[DeadLetter]) -> None: ...

    def append_zone_violations(self, rows: Sequence[ZoneViolation]) -> None:
        """Stores robots' poses found inside keep-out zones (one per pose and zone)."""

    def append_conflicts(self, rows: Sequence[ConflictRow]) -> None:
        """Idempotent on B's identity (ts, row, column, robot_b): of two rows with one
        identity the one naming the later A (by ts_a; on a tie the later append) stays."""

    def append_incidents(
        self, found: Sequence[Incident], found_ms: int, retracted: Sequence[Incident] = ()
    ) -> None:
        """Stores incidents as found at `found_ms` (the detection's clock): one per id, the
        latest finding (by `found_ms`; on a tie the later append) replacing earlier ones.
        `retracted`: incidents found before that a later history no longer holds (a late
        pose broke them); reads leave them out."""


class TimeTravelReader(Protocol):
    """The history at an instant and over a window: poses, chunk writes, the map and the
    robots at a time, the timeline, chunk pixels and the map meta in force (ClickHouse: `reads`)."""

    def poses(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 100_000
    ) -> list[PoseRow]:
        """Poses with from_ms <= event time < to_ms, ordered by time then robot."""

    def poses_downsampled(
        self,
        from_ms: int,
        to_ms: int,
        step_ms: int,
        robot_id: str | None = None,
        limit: int = 100_000,
    ) -> list[PoseRow]:
        """Per robot, its first pose in each step [from_ms + k*step_ms, from_ms + (k+1)*step_ms)
        of from_ms <= event time < to_ms: at most one frame per robot per step, ordered by
        time then robot (a replay's poses at a coarser rate)."""

    def robot_track(
        self, robot_id: str, from_ms: int, to_ms: int, step_ms: int = 0, limit: int = 100_000
    ) -> list[PoseRow]:
        """One robot's poses with from_ms <= event time < to_ms in time order (with step_ms
        > 0, its first in each step [from_ms + k*step_ms, ...)), without planned paths
        (`path` None): a plot's read. A derived view: it may lag `poses` until
        `derive_views` of the same events."""

    def track_buckets(
        self, robot_id: str, from_ms: int, to_ms: int, bucket_ms: int
    ) -> list[TrackBucket]:
        """One robot's poses with from_ms <= event time < to_ms aggregated per absolute
        bucket [k*bucket_ms, (k+1)*bucket_ms) (core/track_buckets.py: `fold_track_buckets`
        is the rule), buckets holding a pose only, in time order: the plots' read, from
        every pose whatever the bucket size. A derived view, as `robot_track`."""

    def chunk_events(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ChunkRow]:
        """Chunk writes with from_ms <= event time < to_ms, in event-time order."""

    def chunk_events_compacted(
        self, from_ms: int, to_ms: int, step_ms: int, limit: int = 100_000
    ) -> list[ChunkRow]:
        """Per chunk and absolute step bucket [k*step_ms, (k+1)*step_ms) within the
        window, only its winning write (greatest (event time, robot id), map_at's rule),
        ordered as chunk_events(): folding them gives the map exactly at every bucket
        boundary and at the window's end (a fast replay's chunk changes)."""

    def timeline(self, from_ms: int, to_ms: int, buckets: int) -> list[TimelineBucket]:
        """[from_ms, to_ms) cut into `timetravel.timeline_buckets(...)`: one TimelineBucket
        per bucket, empty ones included, in time order."""

    def robot_known(self, robot_id: str) -> bool:
        """Whether the robot has any pose in the history."""

    def map_at(self, at_ms: int) -> list[ChunkState]:
        """Per chunk, the write with the greatest (event time, robot id) at or before `at_ms`."""

    def robots_at(
        self, at_ms: int, after: str | None = None, limit: int | None = None
    ) -> list[PoseRow]:
        """Per robot, its pose with the greatest event time at or before `at_ms`, in robot id
        order: only robots whose id sorts after `after`, at most `limit` of them (a page)."""

    def chunk_content(self, content_hash: bytes) -> tuple[int, int, bytes] | None:
        """(width, height, zlib pixels) of a content hash, if stored."""

    def chunk_contents(self, hashes: Sequence[bytes]) -> dict[bytes, tuple[int, int, bytes]]:
        """Many content hashes at once; unknown ones are left out."""

    def latest_meta(self) -> MapMetaSet | None: ...


class SnapshotKeeper(Protocol):
    """The map snapshots the time-travel reads start from (ClickHouse: `snapshots`);
    driven by the snapshot timer."""

    def build_snapshots(self, up_to_ms: int) -> int:
        """Builds the snapshots due up to `up_to_ms`; returns how many were built."""

    def repair_snapshots(self, max_snapshots: int = 144) -> int:
        """Rebuilds at most `max_snapshots` snapshots a late event invalidated (reads skip
        them meanwhile); returns how many. Bounded work, called by the snapshot timer."""


class RetentionKeeper(Protocol):
    """Forgets the history past the retention without changing any state inside it
    (ClickHouse: `retention`); driven by the retention timer."""

    def apply_retention(self, now_ms: int) -> RetentionResult:
        """Forgets the history older than the retention at `now_ms` (the service's clock)
        while the state at every instant from `now_ms - retention` on stays exact: the map,
        the 2019 latest listings, every named chunk's pixels, the map metadata in force."""


class ConflictReader(Protocol):
    """Conflicts and the writes they are found among (mapservice/core/conflicts.py has the
    rule; ClickHouse: `conflict_reads`). Conflicts are written through `HistoryWriter`."""

    def chunk_writes_near(
        self, chunks: Sequence[tuple[int, int]], from_ms: int, to_ms: int
    ) -> list[ChunkRow]:
        """Writes on the given (row, column) chunks with from_ms <= event time <= to_ms,
        in event-time order (the neighbours a new write may conflict with)."""

    def conflicts(self, from_ms: int, to_ms: int, limit: int = 100_000) -> list[ConflictRow]:
        """Conflicts with from_ms <= ts < to_ms, ordered by ts, row, column, robot_b."""

    def conflict_counts(self, from_ms: int, to_ms: int, bucket_ms: int) -> dict[int, int]:
        """Conflicts per bucket [from_ms + k*bucket_ms, ...) of from_ms <= ts < to_ms, keyed
        by the bucket's start; empty buckets are left out."""


class AnnotationReader(Protocol):
    """The operators' annotations and the zone violations found against them
    (ClickHouse: `annotation_reads`)."""

    def annotations_at(self, at_ms: int) -> list[CurrentAnnotation]:
        """The operators' annotations standing at `at_ms` (inclusive), by id."""

    def annotation_edits(
        self, from_ms: int, to_ms: int, limit: int = 10_000
    ) -> list[AnnotationEdit]:
        """The annotation edits with from_ms <= time < to_ms, oldest first."""

    def zone_violations(
        self, from_ms: int, to_ms: int, limit: int = 100_000
    ) -> list[ZoneViolation]:
        """The zone violations with from_ms <= time < to_ms, by time."""


class IncidentReader(Protocol):
    """The incidents found in the history (ClickHouse: `incident_reads`)."""

    def incidents(
        self,
        from_ms: int,
        to_ms: int,
        kinds: Sequence[str] = (),
        robot_id: str | None = None,
        limit: int = 10_000,
    ) -> list[Incident]:
        """The incidents meeting [from_ms, to_ms) (incident_model.meets: start < to_ms,
        end >= from_ms or ongoing), of
        `kinds` (all if empty) and involving `robot_id` (any if None), by start, kind and
        id; as last found, retracted ones left out. An ongoing one meets every window after
        its start, whatever its stored end, which lags (it is written again only now and
        then)."""

    def incidents_per_cell(
        self, from_ms: int, to_ms: int, factor: int, limit: int = 100_000
    ) -> CountedIncidents:
        """Of the first `limit` incidents `incidents` lists for [from_ms, to_ms), how many lie
        in each cell of `factor` finest cells a side (heatmaps.incident_cells); more met?"""


class HeatmapReader(Protocol):
    """The heatmaps' cells (mapservice/core/heatmaps.py's rule; ClickHouse: `heatmap_reads`)."""

    def heatmap_cells(
        self, from_ms: int, to_ms: int, factor: int, limit: int = 1_000_000
    ) -> list[HeatmapCell]:
        """The cells of `factor` finest cells a side holding a sample of [from_ms, to_ms),
        by (i, j), at most `limit`."""


class CommandReader(Protocol):
    """Operators' commands to robots and the robots' answers (ClickHouse: `command_reads`)."""

    def command_events(
        self, from_ms: int, to_ms: int, robot_id: str | None = None, limit: int = 10_000
    ) -> list[StoredCommandEvent]:
        """Operators' commands and the robots' answers with from_ms <= time < to_ms (of
        one robot, if named), oldest first."""


class WebhookRegistry(Protocol):
    """The webhooks operators registered and their replicas' delivery reports
    (mapservice/core/webhook_registry.py; ClickHouse: `webhook_registry`). The API saves
    and removes webhooks and reads the reports; the processors read the webhooks and report."""

    def save_webhook(self, webhook: RegisteredWebhook, changed_ms: int) -> None:
        """Registers `webhook`, or changes it (a resume): the row saved latest (by
        `changed_ms`; on a tie the later save) is the webhook's."""

    def remove_webhook(self, webhook_id: str, changed_ms: int) -> None:
        """Removes the webhook as of `changed_ms` (a later save brings it back)."""

    def webhooks(self) -> list[RegisteredWebhook]:
        """The webhooks registered, oldest first (then by id)."""

    def report_webhooks(self, reports: Sequence[WebhookReport]) -> None:
        """Each replica's latest report per webhook replaces its earlier ones."""

    def webhook_reports(self) -> list[WebhookReport]:
        """Every replica's latest report per webhook, by webhook then replica."""


class VdaReader(Protocol):
    """VDA 5050 vehicles' facts beyond their poses (ClickHouse: `vda_reads`)."""

    def vda_facts(self, robot_id: str, from_ms: int, to_ms: int, limit: int = 10_000) -> VdaFacts:
        """A VDA 5050 vehicle's errors, connection states and latest factsheet."""

    def vda_fleet_facts(self, from_ms: int, to_ms: int, limit: int = 10_000) -> dict[str, VdaFacts]:
        """Every VDA 5050 vehicle's facts of the window (each at most `limit` rows a kind),
        by robot id: those with an error, clear or connection state in it."""

    def connection_states_at(
        self, at_ms: int, since_ms: int, robots: Sequence[str]
    ) -> dict[str, VdaConnectionRow]:
        """Of `robots`, each VDA 5050 vehicle's latest connection state with since_ms <
        time <= at_ms, by robot id (of several at one instant, the last by name: ONLINE)."""


class LegacyQueries(Protocol):
    """The 2019 REST contract's listings (mapservice/core/legacy_query.py has the query
    semantics; ClickHouse: `legacy`)."""

    def list_chunks(self, query: ChunkQuery) -> list[ChunkRow]:
        """Chunk writes passing the query's filters, in `query.order`, `skip` then `limit`
        (the non-`latest` GET /api/chunk-service/chunks)."""

    def list_poses(self, query: PoseQuery) -> list[PoseRow]:
        """Poses passing the query's filters, in `query.order`, `skip` then `limit`
        (the non-`latest` GET /api/coordinate-service/robots)."""


class StoreAdmin(Protocol):
    """The 2019 deletes, counts and closing (ClickHouse: `admin`)."""

    def delete_chunks(self) -> int:
        """Removes every chunk write and map snapshot (2019 DELETE /chunks); returns how
        many writes were removed. Pixels stay until the retention drops their day (nothing
        references them)."""

    def delete_meta(self) -> int:
        """Removes every stored map meta (2019 DELETE /meta); returns how many."""

    def counts(self) -> Counts: ...

    def close(self) -> None: ...


class TableExports(Protocol):
    """The analysts' views read as ClickHouse writes them (CSV, Parquet): only a ClickHouse
    store has it (ClickHouse: `admin`); mapservice/adapters/table_export.py writes the SQL."""

    database: str

    def export_query(self, sql: str, parameters: dict[str, object], fmt: str) -> bytes:
        """The rows of `sql` in ClickHouse's output format `fmt`."""


# `HistoryStore` is the whole store: every role at once (the memory store; ClickHouse's
# `ClickHouseStore` for tests and tools). A composition root hands each component the roles
# it uses (core/store_roles.py): ClickHouse's are adapters of their own over one connection
# (adapters/clickhouse/store.py: `clickhouse_roles`), a whole store is cut into views; no
# component is handed the whole store.
# A new store method goes into the role whose ClickHouse adapter implements it, and is then
# part of HistoryStore too; a new concern gets a role protocol of its own beside these (and
# an adapter module in adapters/clickhouse/, built in `clickhouse_roles`), added to the bases
# below.
class HistoryStore(
    StoreSchema,
    HistoryWriter,
    TimeTravelReader,
    SnapshotKeeper,
    RetentionKeeper,
    ConflictReader,
    AnnotationReader,
    IncidentReader,
    HeatmapReader,
    CommandReader,
    VdaReader,
    WebhookRegistry,
    ChangeFeed,
    LegacyQueries,
    StoreAdmin,
    Protocol,
):
    """The seven-day history, every role at once. Appends are idempotent on each event's
    natural identity."""
