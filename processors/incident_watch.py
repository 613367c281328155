"""Incidents found live (mapservice/core/incident_tracker.py) in the processors: rebuilt with
the views from the store, fed every stored batch's poses, and what is found written
together with the conflicts, before the batch's offsets are committed (like them, the
stored incidents lag the history by up to sink_views_seconds). Touched only in the store
thread: its reads of the history beyond memory (late poses) are store calls. Once stored,
the findings are announced on the live stream (mapservice/core/live_incidents.py: a live
page lists them without asking) and handed to the alerts (incident_alerts.py), which only
queue them.

Two trackers: the poses' incidents (incident_tracker.py) and those of the records stored
beside them (event_incident_tracker.py: zone violations and conflicts, which the views find
and store before they are given here, VDA 5050 states and connection states, commands and
acks), placed by the first's poses. Each reads back only the incidents it finds."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import structlog
from prometheus_client import Counter, Histogram

from mapservice.core.annotations import ZoneViolation
from mapservice.core.event_incident_tracker import EventIncidentTracker, is_event_incident
from mapservice.core.event_incidents import EventRecords, records_of, vda_records_of
from mapservice.core.events import Envelope
from mapservice.core.incident_model import incidents_to_load
from mapservice.core.incident_tracker import IncidentTracker
from mapservice.core.incidents import Incident, IncidentThresholds
from mapservice.core.ports import (
    AnnotationReader,
    CommandReader,
    ConflictReader,
    ConflictRow,
    HistoryWriter,
    IncidentFeed,
    IncidentReader,
    PoseRow,
    TimeTravelReader,
    VdaReader,
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
# The stored incidents' first read asks for this many; more are read in larger reads.
_FIRST_READ_LIMIT = 10_000


def thresholds_of(settings: Settings) -> IncidentThresholds:
    return IncidentThresholds(
        near_miss_m=settings.incident_near_miss_m,
        moving_m_s=settings.incident_moving_m_s,
        stuck_m=settings.incident_stuck_m,
        stuck_ms=round(settings.incident_stuck_s * 1000),
        offline_after_ms=round(settings.robot_offline_after_s * 1000),
        battery_low_percent=settings.incident_battery_low_percent,
        command_ack_timeout_ms=round(settings.incident_command_ack_timeout_s * 1000),
        conflict_gap_ms=round(settings.conflict_window_s * 1000),
    )


class EventSources:
    """The stored records the event incidents are found from, read back for a span."""

    def __init__(
        self,
        annotations: AnnotationReader,
        conflicts: ConflictReader,
        commands: CommandReader,
        vda: VdaReader,
    ) -> None:
        self.annotations, self.conflicts = annotations, conflicts
        self.commands, self.vda = commands, vda

    def read(self, from_ms: int, to_ms: int, robot: str | None) -> EventRecords:
        """The records stored in [from_ms, to_ms), of `robot` (every robot if None)."""
        if to_ms <= from_ms:
            return EventRecords()
        if robot is None:
            facts = self.vda.vda_fleet_facts(from_ms, to_ms, limit=READ_LIMIT)
        else:
            facts = {robot: self.vda.vda_facts(robot, from_ms, to_ms, limit=READ_LIMIT)}
        out = vda_records_of(facts)
        out.violations = [
            v
            for v in self.annotations.zone_violations(from_ms, to_ms, limit=READ_LIMIT)
            if robot in (None, v.robot_id)
        ]
        out.conflicts = [
            c
            for c in self.conflicts.conflicts(from_ms, to_ms, limit=READ_LIMIT)
            if robot in (None, c.robot_b)
        ]
        out.commands = self.commands.command_events(from_ms, to_ms, robot, limit=READ_LIMIT)
        return out


class IncidentWatch:
    def __init__(
        self,
        settings: Settings,
        history: TimeTravelReader,
        incidents: IncidentReader,
        writer: HistoryWriter,
        now_ms: Callable[[], int],
        sources: EventSources,
        alerts: IncidentAlerts | None = None,
        feed: IncidentFeed | None = None,
    ) -> None:
        self.history, self.writer, self.now_ms = history, writer, now_ms
        self.alerts, self.feed = alerts, feed
        self.incidents = incidents
        self.keep_ms = round(settings.incident_memory_s * 1000)
        th = thresholds_of(settings)
        self.tracker = IncidentTracker(
            self._read,
            self._pose_incidents,
            th,
            self.keep_ms,
            round(settings.incident_refresh_s * 1000),
        )
        self.events = EventIncidentTracker(
            sources.read, self._event_incidents, self.tracker.track, th, self.keep_ms
        )
        self.sources = sources
        self.unplaced = EventRecords()  # findings of the views for the next batch

    def stored_incidents(self, from_ms: int, to_ms: int) -> list[Incident]:
        """Every stored incident meeting [from_ms, to_ms), however many: the reader's
        limit is raised until the answer is shorter than it. The rules judge against what
        they load; a read cut at a limit (by start) dropped the newest incidents, those a
        restart most needs, from a busy plant's memory span."""
        limit = _FIRST_READ_LIMIT
        while True:
            found = self.incidents.incidents(from_ms, to_ms, limit=limit)
            if len(found) < limit:
                return found
            limit *= 4

    def _pose_incidents(self, from_ms: int, to_ms: int) -> list[Incident]:
        return [i for i in self.stored_incidents(from_ms, to_ms) if not is_event_incident(i)]

    def _event_incidents(self, from_ms: int, to_ms: int) -> list[Incident]:
        return [i for i in self.stored_incidents(from_ms, to_ms) if is_event_incident(i)]

    def _read(self, from_ms: int, to_ms: int, robot: str | None) -> list[PoseRow]:
        """The stored poses in [from_ms, to_ms) (of `robot`, or all), and each robot's
        newest before from_ms."""
        newest = [p for p in self.history.robots_at(from_ms - 1) if robot in (None, p.robot_id)]
        return newest + self.history.poses(from_ms, to_ms, robot, limit=READ_LIMIT)

    def load(self, horizon_ms: int) -> None:
        """The recent history from the store, and the incidents stored over it."""
        now = self.now_ms()
        since = now - self.keep_ms
        stored = incidents_to_load(
            self.stored_incidents,
            since,
            horizon_ms,
            now,
            self.tracker.th,
        )
        own = [i for i in stored if not is_event_incident(i)]
        self.tracker.load(self._read(since, horizon_ms, None), since, own, now)
        self.events.load(
            self.sources.read(since, horizon_ms, None), since, stored, now, self.tracker.tracks
        )
        self.unplaced = EventRecords()
        if self.alerts is not None:
            self.alerts.seed([*self.tracker.current.values(), *self.events.current.values()])

    def stored_conflicts(self, rows: Sequence[ConflictRow]) -> None:
        """Conflicts the views stored: their incidents are found with the next batch or
        tick (conflicts are written with the findings, after the batch's `find`)."""
        self.unplaced.conflicts += rows

    def find(self, events: Sequence[Envelope], violations: Sequence[ZoneViolation] = ()) -> int:
        """Runs the rules over what the stored batch can change (`violations`: the zone
        violations the views found in it, stored already); returns how many findings now
        wait to be written."""
        with INCIDENT_CHECK_SECONDS.time():
            now = self.now_ms()
            poses = pose_rows_of(events)
            self.tracker.add(poses, now)
            records = records_of(events)
            records.violations += violations
            records.extend(self.unplaced)
            self.events.add(poses, records, now)
            self.unplaced = EventRecords()  # once found: a retried batch finds them again
        return self.waiting()

    def waiting(self) -> int:
        """How many findings wait to be written."""
        t, e = self.tracker, self.events
        return len(t.found) + len(t.retracted) + len(e.found) + len(e.retracted)

    def tick(self) -> None:
        """Robots that fell silent as the clock moved, commands left without an ack, and
        the conflicts stored since the last batch."""
        now = self.now_ms()
        self.tracker.tick(now)
        self.judge_stored_conflicts(now)
        self.events.tick(now)

    def judge_stored_conflicts(self, now_ms: int | None = None) -> None:
        """The conflicts stored since the last batch, judged now: called as they are stored,
        before their batches' offsets are committed. Left to the next batch or tick, a stop
        in between committed conflicts never judged, and a restart after more than
        `incident_memory_s` (which reads back only that span) never judged them."""
        if self.unplaced.conflicts:
            self.events.add([], self.unplaced, self.now_ms() if now_ms is None else now_ms)
            self.unplaced = EventRecords()  # once found: a failed read keeps them for the next

    def write(self) -> int:
        """Stores the findings since the last call; returns how many rows."""
        found, retracted = self.tracker.take()
        more_found, more_retracted = self.events.take()
        if not (found or retracted or more_found or more_retracted):
            return 0
        now = self.now_ms()
        try:
            self.writer.append_incidents([*found, *more_found], now, [*retracted, *more_retracted])
        except BaseException:
            self.tracker.give_back(found, retracted)  # written with the next try
            self.events.give_back(more_found, more_retracted)
            raise
        found, retracted = [*found, *more_found], [*retracted, *more_retracted]
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
        self.events.forget(now)
        if self.alerts is not None:
            held = [*self.tracker.current, *self.events.current]
            self.alerts.keep(held, len(held))
        return len(found) + len(retracted)
