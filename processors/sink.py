"""The history sink: stores batches on the store thread until they are in, and the pure
part (raw Kafka values to what the store appends)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping

import msgspec
import structlog
from prometheus_client import Counter, Gauge, Histogram

from mapservice.core.events import DeadLetter, Envelope, decode, decode_dead_letter
from mapservice.core.ports import HistoryWriter, LiveFeed
from mapservice.core.retention import DAY_MS, DEFAULT_RETENTION_MS, expired
from mapservice.runtime.insert_health import InsertHealth
from mapservice.runtime.retry import until_done

from .store_thread import StoreThread

log = structlog.get_logger(__name__)

STORED = Counter("mapservice_sink_events_total", "Events appended to the history", ["topic"])
INSERT_SECONDS = Histogram(
    "mapservice_sink_insert_seconds",
    "Duration of one history insert",
    buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5),
)
DERIVE_SECONDS = Histogram(
    "mapservice_sink_derive_views_seconds",
    "Duration of one insert into the derived pose views (many batches)",
    buckets=(0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5),
)
INSERT_FAILURES = Counter(
    "mapservice_sink_insert_failures_total", "Inserts that failed and were retried"
)
# The state behind readiness's `history_store` (mapservice/runtime/insert_health.py): a
# counter of failures cannot say whether the history is being stored now.
INSERT_FAILING = Gauge(
    "mapservice_history_insert_failing",
    "1 while history inserts fail and are retried (nothing new is stored), 0 once one succeeds",
)
INSERT_FAILING_SINCE = Gauge(
    "mapservice_history_insert_failing_since_timestamp_seconds",
    "Unix time of the first failed history insert of the current failure; 0 while inserts succeed",
)
EXPIRED = Counter(
    "mapservice_sink_expired_events_total",
    "Events not stored: older than the retention at the service's clock (records read "
    "again from Kafka after the retention dropped their day)",
    ["topic"],
)
# A whole topic read again is millions of such events: one line a minute says so.
EXPIRED_LOG_EVERY_S = 60.0
LAST_INSERT = Gauge(
    "mapservice_history_last_insert_timestamp_seconds",
    "Unix time of the last successful history insert (0: none yet)",
)


class HistorySink:
    """Stores through `writer` on `thread`, the one that talks to the store (store_thread.py; a thread of
    its own when none is given), and records whether the inserts succeed."""

    def __init__(
        self,
        writer: HistoryWriter,
        live: LiveFeed | None = None,
        health: InsertHealth | None = None,
        thread: StoreThread | None = None,
        retention_ms: int = DEFAULT_RETENTION_MS,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.writer = writer
        self.live = live
        self.retention_ms = retention_ms
        self.monotonic = monotonic
        self._expired_since_log: dict[str, int] = {}  # per topic, dropped since the last line
        self._expired_logged_at = -math.inf  # monotonic
        self.thread = thread or StoreThread()
        # Whether the inserts succeed: readiness, the metrics below, the UI's banner.
        self.health = health = health or InsertHealth()
        INSERT_FAILING.set_function(lambda: float(health.failing))
        INSERT_FAILING_SINCE.set_function(lambda: health.failing_since_s or 0.0)
        LAST_INSERT.set_function(lambda: health.last_stored_s or 0.0)

    def unexpired(self, topic: str, events: list[Envelope], now_ms: int) -> list[Envelope]:
        """`events` but those the retention at `now_ms` (the service's clock) has already
        forgotten: stored, they would bring a dropped day back, with the snapshots, views and
        conflicts built over it, until the next retention step. Each dropped one is counted
        (EXPIRED); a log line a minute at most says how many."""
        kept = [e for e in events if not expired(e, now_ms, self.retention_ms)]
        if len(kept) == len(events):
            return events
        dropped = len(events) - len(kept)
        EXPIRED.labels(topic).inc(dropped)
        self._expired_since_log[topic] = self._expired_since_log.get(topic, 0) + dropped
        if self.monotonic() - self._expired_logged_at >= EXPIRED_LOG_EVERY_S:
            self._expired_logged_at = self.monotonic()
            counts, self._expired_since_log = self._expired_since_log, {}
            log.warning(
                "events older than the retention not stored",
                retention_days=self.retention_ms / DAY_MS,
                boundary_ms=now_ms - self.retention_ms,
                dropped=counts,
            )
        return kept

    async def run(self, fn, *args):
        return await self.thread.run(fn, *args)

    async def _insert(self, fn, batch) -> None:
        """One insert attempt, its outcome recorded in `health` (per store method: one
        table's refusal is not cleared by another's success)."""
        what = getattr(fn, "__name__", "insert")
        try:
            await self.run(fn, batch)
        except Exception as exc:  # noqa: BLE001 - whatever the store raises; the caller retries
            if self.health.failed(exc, what):
                log.error(
                    "history not stored: inserts fail; retried until they succeed, "
                    "nothing unstored is committed",
                    reason=self.health.reason(),
                )
            raise
        if (failed_s := self.health.stored(what)) is not None:
            log.warning("history stored again: inserts succeed", failed_s=round(failed_s, 1))

    async def insert_until_done(self, fn, batch, counts: Mapping[str, int]) -> None:
        """Stores `batch` with `fn`, retrying until it is in; then counts it as stored,
        per topic (`counts`: how many of the batch came from each topic)."""
        # Retried, never skipped: acknowledging a batch that is not stored would lose it.
        async for attempt in until_done(
            "history insert", 0.2, INSERT_FAILURES.inc, topics=sorted(counts), batch=len(batch)
        ):
            with attempt:
                started = time.monotonic()
                await self._insert(fn, batch)
        INSERT_SECONDS.observe(time.monotonic() - started)
        for topic, count in counts.items():
            STORED.labels(topic).inc(count)

    async def derive_until_done(self, batch) -> None:
        """Brings the derived pose views up to a stored `batch`, retrying until it is done
        (its offsets are committed after this: a batch whose views are missing is never
        acknowledged)."""
        async for attempt in until_done(
            "history views", 0.2, INSERT_FAILURES.inc, batch=len(batch)
        ):
            with attempt:
                started = time.monotonic()
                await self._insert(self.writer.derive_views, batch)
        DERIVE_SECONDS.observe(time.monotonic() - started)


def split_events(values: Iterable[bytes], now_ms: int) -> tuple[list[Envelope], list[DeadLetter]]:
    """Decodes envelopes; a record that is not one becomes a dead letter, not a crash."""
    events: list[Envelope] = []
    bad: list[DeadLetter] = []
    for value in values:
        try:
            events.append(decode(value))
        except (msgspec.DecodeError, TypeError, UnicodeDecodeError) as exc:
            bad.append(
                DeadLetter(
                    reason="undecodable_event",
                    detail=str(exc)[:500],
                    mqtt_topic="",
                    payload=value or b"",
                    receive_time_ms=now_ms,
                    gateway="processors",
                )
            )
    return events, bad


def decode_dead_letters(values: Iterable[bytes], now_ms: int) -> list[DeadLetter]:
    out = []
    for value in values:
        try:
            out.append(decode_dead_letter(value))
        except (msgspec.DecodeError, TypeError, UnicodeDecodeError) as exc:
            out.append(
                DeadLetter(
                    reason="undecodable_dead_letter",
                    detail=str(exc)[:500],
                    mqtt_topic="",
                    payload=value or b"",
                    receive_time_ms=now_ms,
                    gateway="processors",
                )
            )
    return out
