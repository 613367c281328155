"""The processors' live views: the latest map (advertised on MQTT), the robots, conflicts.

Fed by the history consumer after each insert (`on_stored`), so a view never shows, and an
advertisement never names, a write the API cannot serve yet. The views are rebuilt from
ClickHouse whenever faust assigns partitions (start-up, restart, rebalance), before any
event of those partitions is consumed: the history is the changelog. The rules are pure
functions in `mapservice/core/liveview.py` and `mapservice/core/conflicts.py`. Their store
calls run on the processors' one store thread, handed to them at construction
(store_thread.py).

Each batch's conflicts are found after its insert (`find_conflicts`) and written together
with the pose views (`write_conflicts`, from `HistoryConsumer.settle`), before its offsets
are committed: like those views, the conflicts lag the history by up to sink_views_seconds.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

import structlog
from mapservice.processors.conflict_recorder import (
    UnwrittenConflicts,
    find_conflicts,
    write_conflicts,
)
from mapservice.processors.zone_watch import KeepOutWatch
from prometheus_client import Counter, Gauge, Histogram

from mapservice.adapters.clock import SystemClock
from mapservice.core.annotations import (
    ANNOTATION_EVENTS,
    AnnotationRemoved,
    Zone,
    zone_advertisement,
)
from mapservice.core.conflicts import RecentWrites
from mapservice.core.events import ChunkUpdated, Envelope, pose_of
from mapservice.core.liveview import (
    RobotState,
    advertisement,
    apply_chunks,
    apply_poses,
    online_robots,
)
from mapservice.core.ports import ChunkRow, HistoryStore
from mapservice.runtime.retry import until_done
from mapservice.settings import Settings

from .store_thread import StoreThread

log = structlog.get_logger(__name__)

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
VIEW_CHANGES = Counter("mapservice_latest_map_changes_total", "Changes of the live latest map")
ADS_DROPPED = Counter(
    "mapservice_advertisements_dropped_total",
    "Advertisements dropped because too many were waiting to be encoded",
)
MAX_PENDING_ADS = 10_000
# Conflict neighbours of live batches come from memory (mapservice.core.conflicts.RecentWrites)
# when the window is short enough to keep its writes; older ones from the store.
RECENT_MAX_WINDOW_MS = 600_000
RECENT_SLACK_MS = 120_000
RECENT_MAX_ROWS = 200_000
ZONE_VIOLATIONS = Counter(
    "mapservice_zone_violations_total", "Stored poses found inside a keep-out zone"
)
ROBOTS_ONLINE = Gauge("mapservice_robots_online", "Robots heard from within robot_offline_after_s")


class Advertiser(Protocol):
    def start(self) -> None: ...

    def publish(self, payload: dict) -> bool: ...

    def publish_to(self, topic: str, payload: dict) -> bool: ...

    def stop(self) -> None: ...


class LiveViews:
    def __init__(
        self,
        settings: Settings,
        store: HistoryStore,
        advertiser: Advertiser | None,
        store_thread: StoreThread,
        now_ms: Callable[[], int] = SystemClock().now_ms,
    ) -> None:
        self.settings = settings
        self.store = store
        # The processors' one thread for store calls: the history's inserts go through it
        # too, so a load or conflict check sees exactly the batches stored before it.
        self.store_thread = store_thread
        self.advertiser = advertiser
        self.now_ms = now_ms
        self.latest: dict = {}  # (row, column) -> ChunkState
        self.robots: dict[str, RobotState] = {}
        self.zone_ids: set[str] = set()  # the zones standing now: a removal of one is advertised
        self.keep_out = KeepOutWatch()  # touched only in the store thread
        self.online: set[str] = set()
        self.loaded = False
        self.recent: RecentWrites | None = None  # touched only in the store thread
        self.unwritten = UnwrittenConflicts()  # likewise
        self._recent_pruned_ms = 0
        self.window_ms = int(settings.conflict_window_s * 1000)
        # Encoding an advertisement (base64 + PNG) takes ~2 ms: one thread of its own keeps
        # that off the event loop and keeps each chunk's advertisements in order.
        self._ad_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="advertiser")
        self._pending = 0
        self._pending_lock = threading.Lock()

    # --- blocking parts: run in the store thread ------------------------------------------

    def load(self) -> None:
        """Rebuilds both views from the history (latest over all stored event times)."""
        horizon = self.now_ms() + int(self.settings.max_future_skew_s * 1000) + 86_400_000
        latest = {(c.row, c.column): c for c in self.store.map_at(horizon)}
        robots = {
            p.robot_id: RobotState(
                p.robot_id,
                p.ts_ms,
                p.receive_time_ms,
                p.receive_time_ms,
                (p.x, p.y, p.z),
                p.battery_level,
                p.charging,
                p.loaded,
            )
            for p in self.store.robots_at(horizon)
        }
        self.latest, self.robots = latest, robots
        self.zone_ids = {
            c.annotation_id
            for c in self.store.annotations_at(horizon)
            if isinstance(c.annotation, Zone)
        }
        self.keep_out.rebuild(self.store, horizon)
        self.recent = self._load_recent()
        self.loaded = True
        log.info("live views rebuilt from the history", chunks=len(latest), robots=len(robots))

    def _recent_span_ms(self) -> int:
        return 2 * self.window_ms + RECENT_SLACK_MS

    def _load_recent(self) -> RecentWrites | None:
        if self.window_ms > RECENT_MAX_WINDOW_MS:
            return None
        now = self.now_ms()
        since = now - self._recent_span_ms()
        rows = self.store.chunk_events(
            since,
            now + int(self.settings.max_future_skew_s * 1000) + 86_400_000,
            limit=RECENT_MAX_ROWS,
        )
        if len(rows) >= RECENT_MAX_ROWS:
            return None  # too busy to hold in memory: every batch asks the store
        self._recent_pruned_ms = now
        return RecentWrites(since, rows)

    def find_conflicts(self, events: Sequence[Envelope]) -> int:
        """Finds every conflict the stored batch creates or changes, for `write_conflicts`;
        returns how many rows now wait to be written."""
        new = [
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
        now = self.now_ms()
        if self.recent is not None and now - self._recent_pruned_ms > 10_000:
            self.recent.forget_before(now - self._recent_span_ms())
            self._recent_pruned_ms = now
        with CONFLICT_CHECK_SECONDS.time():
            self.unwritten.add(find_conflicts(self.store, new, self.window_ms, self.recent))
        return len(self.unwritten)

    def write_conflicts(self) -> int:
        """Stores the conflicts found since the last call; returns how many rows. Called
        with the pose views, before offsets are committed (HistoryConsumer.settle): one
        insert per several batches instead of one per batch (each insert has a fixed cost
        of ~10 ms on chDB)."""
        if not self.unwritten:
            return 0
        rows = self.unwritten.rows()
        with CONFLICT_WRITE_SECONDS.time():
            write_conflicts(self.store, rows, self.recent)
        self.unwritten.clear()
        CONFLICTS.inc(len(rows))
        return len(rows)

    # --- in the event loop ----------------------------------------------------------------

    async def on_stored(self, events: Sequence[Envelope]) -> None:
        """After a batch is in the history, before it is acknowledged."""
        if not self.loaded:
            # The rebuild at assignment failed: rebuild now (this batch is in it already,
            # so its changes go unadvertised) rather than let older writes win.
            await self._until_done(lambda _: self.load(), None)
        if any(isinstance(e.payload, ChunkUpdated) for e in events):
            await self._until_done(self.find_conflicts, events)
            for e in apply_chunks(self.latest, events):
                VIEW_CHANGES.inc()
                self.advertise(e)
        if any(pose_of(e.payload) is not None for e in events):
            apply_poses(self.robots, events)
        zones_changed = False
        for e in events:
            if isinstance(e.payload, ANNOTATION_EVENTS):
                zones_changed |= self.zone_edited(e)
        if zones_changed:
            horizon = self.now_ms() + int(self.settings.max_future_skew_s * 1000) + 86_400_000
            await self._until_done(lambda _: self.keep_out.rebuild(self.store, horizon), None)
        if self.keep_out.ids and any(pose_of(e.payload) is not None for e in events):
            found = self.keep_out.violations(events)
            if found:
                await self._until_done(self.store.append_zone_violations, found)
                ZONE_VIOLATIONS.inc(len(found))

    def zone_edited(self, e: Envelope) -> bool:
        """Advertises an edit that creates, changes or removes a zone (robots then fetch
        the masks); edits of points of interest are not the robots' business."""
        p = e.payload
        was_zone = p.annotation_id in self.zone_ids
        is_zone = not isinstance(p, AnnotationRemoved) and isinstance(p.annotation, Zone)
        if is_zone:
            self.zone_ids.add(p.annotation_id)
        else:
            self.zone_ids.discard(p.annotation_id)
        if (was_zone or is_zone) and self.advertiser is not None:
            ad = zone_advertisement(
                p.annotation_id,
                e.type.removeprefix("annotation."),
                e.event_time_ms,
                p.author,
                self.settings.public_base_url,
            )
            self._ad_thread.submit(self._publish_zone, ad)
        return was_zone or is_zone

    def _publish_zone(self, ad: dict) -> None:
        try:
            self.advertiser.publish_to(self.settings.zone_advertisement_topic, ad)
        except Exception as exc:  # best effort, as chunk advertisements
            log.warning("zone advertisement failed", error=str(exc))

    def advertise(self, e: Envelope) -> None:
        """Hands the advertisement to the advertiser thread; never waits for it."""
        if self.advertiser is None:
            return
        with self._pending_lock:
            if self._pending >= MAX_PENDING_ADS:
                ADS_DROPPED.inc()
                return
            self._pending += 1
        self._ad_thread.submit(self._publish, e)

    def _publish(self, e: Envelope) -> None:
        try:
            self.advertiser.publish(advertisement(e, self.settings.public_base_url))
        except Exception as exc:  # advertising is best effort; the history is not at stake
            log.warning("advertisement failed", error=str(exc))
        finally:
            with self._pending_lock:
                self._pending -= 1

    def flush(self) -> None:
        """Waits until every advertisement handed over so far was published (tests)."""
        self._ad_thread.submit(lambda: None).result()

    def close(self) -> None:
        self._ad_thread.shutdown(wait=True)

    def check_presence(self) -> tuple[set[str], set[str]]:
        """Logs robots going online/offline; returns (came online, went offline)."""
        online = online_robots(self.robots, self.now_ms(), self.settings.robot_offline_after_s)
        came, went = online - self.online, self.online - online
        for robot in sorted(came):
            log.info("robot online", robot=robot)
        for robot in sorted(went):
            state = self.robots.get(robot)  # gone from a rebuilt view if its history is
            log.info(
                "robot offline",
                robot=robot,
                silent_s=None
                if state is None
                else round((self.now_ms() - state.last_seen_ms) / 1000, 1),
            )
        self.online = online
        ROBOTS_ONLINE.set(len(online))
        return came, went

    async def write_conflicts_until_done(self) -> None:
        """`write_conflicts` on the store thread, retried until it succeeds."""
        if len(self.unwritten):  # nothing to hand to the store thread
            await self._until_done(lambda _: self.write_conflicts(), None)

    async def _until_done(self, fn, batch) -> None:
        # Retried: acknowledging the batch without its conflicts and views would lose them.
        async for attempt in until_done("live views update", 0.2):
            with attempt:
                await self.store_thread.run(fn, batch)

    async def rebuild(self) -> None:
        """After a partition assignment, before any event of it is applied: the views as the
        history holds them, and the advertiser running."""
        # Submitted to the store thread before any batch of the new assignment is inserted
        # there, so the rebuilt views hold exactly what was stored before.
        self.loaded = False
        try:
            await self.store_thread.run(self.load)
        except Exception as exc:  # raising here would stop the consumer; retried in on_stored
            log.error("live views rebuild failed; retried with the next batch", error=str(exc))
        if self.advertiser is not None:
            self.advertiser.start()
