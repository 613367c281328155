"""The processors' live views: the latest map (advertised on MQTT), the robots, the zones,
conflicts and incidents, each a part of its own (latest_map.py, presence.py, zone_watch.py,
conflict_recorder.py, incident_watch.py) with its advertisements on one queue (advertising.py); `LiveViews`
drives them together.

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

import time
from collections.abc import Callable, Sequence
from typing import Any

import structlog

from mapservice.adapters.clock import SystemClock
from mapservice.core.annotations import ANNOTATION_EVENTS
from mapservice.core.commands import CommandAcknowledged, CommandIssued
from mapservice.core.events import (
    Envelope,
    VdaConnectionReported,
    VdaStateReported,
    pose_of,
)
from mapservice.core.liveview import RobotState
from mapservice.core.ports import (
    AnnotationReader,
    ChunkState,
    CommandReader,
    ConflictReader,
    HistoryWriter,
    IncidentFeed,
    IncidentReader,
    TimeTravelReader,
    VdaReader,
)
from mapservice.runtime.retry import until_done
from mapservice.settings import Settings

from .advertising import AdvertisementQueue, Advertiser
from .conflict_recorder import ConflictWatch
from .incident_alerts import IncidentAlerts
from .incident_watch import EventSources, IncidentWatch
from .latest_map import LatestMap
from .presence import Presence
from .store_thread import StoreThread
from .stream_clock import StreamClock
from .webhook_delivery import WebhookDeliveries
from .zone_watch import ZONE_VIOLATIONS, Zones

log = structlog.get_logger(__name__)
# What, besides poses, the incidents are found from (event_incidents.py)
INCIDENT_RECORDS = (VdaStateReported, VdaConnectionReported, CommandIssued, CommandAcknowledged)

__all__ = ["Advertiser", "LiveViews"]


class LiveViews:
    """Rebuilt from the map and robots at an instant (`history`), the standing zones
    (`annotations`) and the writes near new ones (`conflicts`); the conflicts and zone
    violations found are stored through `writer`, the incidents announced on `live`
    (found also from the commands' acks, `commands`, and VDA 5050 vehicles' states, `vda`)."""

    def __init__(
        self,
        settings: Settings,
        *,
        history: TimeTravelReader,
        annotations: AnnotationReader,
        conflicts: ConflictReader,
        incidents: IncidentReader,
        commands: CommandReader,
        vda: VdaReader,
        writer: HistoryWriter,
        advertiser: Advertiser | None,
        store_thread: StoreThread,
        now_ms: Callable[[], int] = SystemClock().now_ms,
        webhooks: WebhookDeliveries | None = None,
        live: IncidentFeed | None = None,
    ) -> None:
        self.settings = settings
        self.history = history
        self.writer = writer
        # The processors' one thread for store calls: the history's inserts go through it
        # too, so a load or conflict check sees exactly the batches stored before it.
        self.store_thread = store_thread
        self.advertiser = advertiser
        self.now_ms = now_ms
        # silences (who is online, `offline` incidents) are judged by the stream's clock
        self.clock = StreamClock(now_ms)
        self.ads = (
            None if advertiser is None else AdvertisementQueue(advertiser, settings.public_base_url)
        )
        self.map = LatestMap(self.ads)
        self.presence = Presence(settings.robot_offline_after_s)
        self.zones = Zones(
            history,
            annotations,
            self.ads,
            settings.zone_advertisement_topic,
            settings.public_base_url,
        )
        self.conflicts = ConflictWatch(
            history, conflicts, writer, int(settings.conflict_window_s * 1000), now_ms
        )
        alerts = IncidentAlerts(settings.incident_alert_topic_root, self.ads, webhooks)
        self.incidents = IncidentWatch(
            settings,
            history,
            incidents,
            writer,
            self.clock.now_ms,
            EventSources(annotations, conflicts, commands, vda),
            alerts=alerts,
            feed=live,
        )
        self.loaded = False

    @property
    def latest(self) -> dict[tuple[int, int], ChunkState]:
        return self.map.latest

    @property
    def robots(self) -> dict[str, RobotState]:
        return self.presence.robots

    def _horizon_ms(self) -> int:
        """Later than any stored event time: the views hold the latest of everything."""
        return self.now_ms() + int(self.settings.max_future_skew_s * 1000) + 86_400_000

    # --- blocking parts: run in the store thread ------------------------------------------

    def load(self) -> None:
        """Rebuilds every view from the history (latest over all stored event times)."""
        horizon = self._horizon_ms()
        # Each part's seconds are logged: a rebuild runs on the store thread, and one longer
        # than the consumer's poll interval costs the group another rebalance.
        took: dict[str, float] = {}
        parts: tuple[tuple[str, Callable[[], None]], ...] = (
            ("map", lambda: self.map.load(self.history, horizon)),
            ("presence", lambda: self.presence.load(self.history, horizon)),
            ("zones", lambda: self.zones.load(horizon)),
            ("conflicts", lambda: self.conflicts.load(horizon)),
            ("incidents", lambda: self.incidents.load(horizon)),
        )
        for name, part in parts:
            started = time.perf_counter()
            part()
            took[name] = round(time.perf_counter() - started, 3)
        self.loaded = True
        log.info(
            "live views rebuilt from the history",
            chunks=len(self.latest),
            robots=len(self.robots),
            took_s=took,
        )

    def find_conflicts(self, events: Sequence[Envelope]) -> int:
        """Finds every conflict the stored batch creates or changes, for `write_conflicts`;
        returns how many rows now wait to be written."""
        return self.conflicts.find(events)

    def write_conflicts(self) -> int:
        """Stores the conflicts found since the last call; returns how many rows. Called
        with the pose views, before offsets are committed (HistoryConsumer.settle): one
        insert per several batches instead of one per batch (each insert has a fixed cost
        of ~10 ms on chDB)."""
        return self.conflicts.write()

    def write_found(self) -> int:
        """Stores the conflicts and incidents found since the last call; returns how many
        rows. Called with the pose views, before offsets are committed
        (HistoryConsumer.settle)."""
        rows = self.conflicts.unwritten.rows()
        written = self.write_conflicts()
        self.incidents.stored_conflicts(rows)
        self.incidents.judge_stored_conflicts()  # their incidents written with them
        return written + self.incidents.write()

    # --- in the event loop ----------------------------------------------------------------

    async def on_stored(self, events: Sequence[Envelope]) -> None:
        """After a batch is in the history, before it is acknowledged."""
        self.clock.stored(events)
        if not self.loaded:
            # The rebuild at assignment failed: rebuild now (this batch is in it already,
            # so its changes go unadvertised) rather than let older writes win.
            await self._until_done(lambda _: self.load(), None)
        if LatestMap.touched_by(events):
            await self._until_done(self.find_conflicts, events)
            self.map.apply(events)
        has_poses = any(pose_of(e.payload) is not None for e in events)
        if has_poses:
            self.presence.apply(events)
        zones_changed = False
        for e in events:
            if isinstance(e.payload, ANNOTATION_EVENTS):
                zones_changed |= self.zones.edited(e)
        if zones_changed:
            horizon = self._horizon_ms()
            await self._until_done(lambda _: self.zones.rebuild_keep_out(horizon), None)
        found = self.zones.violations(events) if has_poses else []
        if found:
            await self._until_done(self.writer.append_zone_violations, found)
            ZONE_VIOLATIONS.inc(len(found))
        if has_poses or any(isinstance(e.payload, INCIDENT_RECORDS) for e in events):
            # after the violations are stored: their incidents are what the store holds
            await self._until_done(lambda evs: self.incidents.find(evs, found), events)

    def flush(self) -> None:
        """Waits until every advertisement handed over so far was published (tests)."""
        if self.ads is not None:
            self.ads.flush()

    def close(self) -> None:
        if self.ads is not None:
            self.ads.close()

    def check_presence(self) -> tuple[set[str], set[str]]:
        """Logs robots going online/offline; returns (came online, went offline)."""
        return self.presence.check(self.clock.now_ms())

    async def tick(self) -> None:
        """Once a second: robots going online and offline, and the incidents of silences.
        A store that fails meanwhile (restarting) fails this tick only: raised out of the
        app's timer, it would crash the app, its timers (snapshots, retention) with it."""
        self.check_presence()
        if self.loaded:
            try:
                await self.store_thread.run(self.incidents.tick)
            except Exception as exc:  # noqa: BLE001 - whatever the store raises; the next tick tries again
                log.warning("incidents not judged this tick", error=str(exc))

    async def write_found_until_done(self) -> None:
        """`write_found` on the store thread, retried until it succeeds."""
        if len(self.conflicts.unwritten) or self.incidents.waiting():
            await self._until_done(lambda _: self.write_found(), None)

    async def _until_done(self, fn: Callable[[Any], object], batch: Any) -> None:
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
