"""Incidents found live (mapservice/core/incident_tracker.py) in the processors: rebuilt with
the views from the store, fed every stored batch's poses, and what is found written
together with the conflicts, before the batch's offsets are committed (like them, the
stored incidents lag the history by up to sink_views_seconds). Touched only in the store
thread: its reads of the history beyond memory (late poses) are store calls. Once stored,
the findings are announced on the live stream (mapservice/core/live_incidents.py: a live
page lists them without asking) and handed to the alerts (incident_alerts.py), which only
queue them."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import structlog
from prometheus_client import Counter, Histogram

from mapservice.core.events import Envelope
from mapservice.core.incident_tracker import IncidentTracker
from mapservice.core.incidents import IncidentThresholds
from mapservice.core.ports import (
    HistoryWriter,
    IncidentFeed,
    IncidentReader,
    PoseRow,
    TimeTravelReader,
)
from mapservice.core.stored_rows import pose_rows_of
from mapservice.settings import Settings

from .incident_alerts import IncidentAlerts

INCIDENTS = Counter(
    "mapservice_incidents_found_total",
    "Incident findings written (new incidents and changes of known ones)",
    ["kind"],
)
INCIDENTS_RETRACTED = Counter(
    "mapservice_incidents_retracted_total", "Incidents a late pose broke, retracted"
)
INCIDENT_CHECK_SECONDS = Histogram(
    "mapservice_incidents_check_seconds",
    "Duration of finding one stored batch's incidents",
    buckets=(0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1),
)
log = structlog.get_logger(__name__)

# A late pose's read of the history beyond memory: one window of every robot's poses.
READ_LIMIT = 5_000_000


def thresholds_of(settings: Settings) -> IncidentThresholds:
    return IncidentThresholds(
        near_miss_m=settings.incident_near_miss_m,
        moving_m_s=settings.incident_moving_m_s,
        stuck_m=settings.incident_stuck_m,
        stuck_ms=round(settings.incident_stuck_s * 1000),
        offline_after_ms=round(settings.robot_offline_after_s * 1000),
        battery_low_percent=settings.incident_battery_low_percent,
    )


class IncidentWatch:
    def __init__(
        self,
        settings: Settings,
        history: TimeTravelReader,
        incidents: IncidentReader,
        writer: HistoryWriter,
        now_ms: Callable[[], int],
        alerts: IncidentAlerts | None = None,
        feed: IncidentFeed | None = None,
    ) -> None:
        self.history, self.writer, self.now_ms = history, writer, now_ms
        self.alerts, self.feed = alerts, feed
        self.keep_ms = round(settings.incident_memory_s * 1000)
        self.tracker = IncidentTracker(
            self._read,
            incidents.incidents,
            thresholds_of(settings),
            self.keep_ms,
            round(settings.incident_refresh_s * 1000),
        )

    def _read(self, from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        """The stored poses in [from_ms, to_ms) (of `robot`, or all), and each robot's
        newest before from_ms."""
        newest = [p for p in self.history.robots_at(from_ms - 1) if robot in (None, p.robot_id)]
        return newest + self.history.poses(from_ms, to_ms, robot, limit=READ_LIMIT)

    def load(self, horizon_ms: int) -> None:
        """The recent history from the store, and the incidents stored over it."""
        now = self.now_ms()
        since = now - self.keep_ms
        stored = self.tracker.read_incidents(since - self.tracker.th.lookback_ms, horizon_ms)
        self.tracker.load(self._read(since, horizon_ms, None), since, stored, now)
        if self.alerts is not None:
            self.alerts.seed(self.tracker.current.values())

    def find(self, events: Sequence[Envelope]) -> int:
        """Runs the rules over what the stored batch can change; returns how many findings
        now wait to be written."""
        with INCIDENT_CHECK_SECONDS.time():
            self.tracker.add(pose_rows_of(events), self.now_ms())
        return len(self.tracker.found) + len(self.tracker.retracted)

    def tick(self) -> None:
        """Robots that fell silent as the clock moved."""
        self.tracker.tick(self.now_ms())

    def write(self) -> int:
        """Stores the findings since the last call; returns how many rows."""
        found, retracted = self.tracker.take()
        if not found and not retracted:
            return 0
        now = self.now_ms()
        try:
            self.writer.append_incidents(found, now, retracted)
        except BaseException:
            self.tracker.give_back(found, retracted)  # written with the next try
            raise
        if self.feed is not None:
            # Best effort, like the rest of the live stream: the findings are stored, and a
            # page that missed the announcement reads them from the list.
            try:
                self.feed.publish_incidents(found, retracted, now)
            except Exception as exc:  # noqa: BLE001 - whatever the feed raises; logged
                log.warning("incidents not announced on the live stream", error=str(exc))
        for incident in found:
            INCIDENTS.labels(incident.kind).inc()
        INCIDENTS_RETRACTED.inc(len(retracted))
        if self.alerts is not None:
            self.alerts.announce(found, retracted, now)
        self.tracker.forget(now)
        if self.alerts is not None:
            self.alerts.keep(self.tracker.current, len(self.tracker.current))
        return len(found) + len(retracted)
