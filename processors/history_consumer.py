"""Moves the event topics into the history in batches, committing offsets once they are
stored and the derived pose views and conflicts brought up to them.

At-least-once: offsets are committed only after their events are in the history (with
the live views, conflicts and derived pose views that come from them); a crash or
rebalance before that re-delivers them, and the history's natural-identity keys absorb
the repeat.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, TypeVar

import mode
import structlog
from prometheus_client import Counter, Gauge, Histogram

from mapservice.adapters.clock import SystemClock
from mapservice.core.ports import EventSource, SourceRecord
from mapservice.runtime.health import Heartbeat
from mapservice.runtime.retry import until_done

from .batch_window import batch_window, smoothed
from .sink import split_events

if TYPE_CHECKING:
    from .sink import HistorySink
    from .views import LiveViews

log = structlog.get_logger(__name__)
T = TypeVar("T")

# A poll that waited this long (or a whole shortest window) and found nothing means the
# stream holds nothing more yet.
CAUGHT_UP_WAIT_S = 0.05
# While a batch's store, its views or a rebuild runs longer than this, the source is asked
# to keep this member in its group this often (EventSource.stay_in_group): well inside the
# shortest max.poll.interval.ms the consumer is given (10 s, kafka_batch_source.py).
STAY_IN_GROUP_EVERY_S = 2.0

COMMIT_FAILURES = Counter(
    "mapservice_sink_commit_failures_total",
    "Batches stored but not committed (they will be re-delivered)",
)
# End to end, per stored event: from the robot's timestamp (includes its clock's skew) and
# from the gateway's receive time (the service's own latency) to the moment the insert
# holding it returned, i.e. to queryable.
# 25 ms steps up to 0.3 s: the live bound at 1,000 robots (p99 <= 0.3 s) can then be read
# off the histogram exactly, by an alert, a dashboard or `mapservice bench ingest`.
STORED_LATENCY_BUCKETS = (
    *(round(0.025 * i, 3) for i in range(1, 13)),
    0.35,
    0.4,
    0.5,
    0.75,
    1,
    2,
    5,
    10,
    30,
    60,
    300,
    3600,
)
EVENT_TO_STORED = Histogram(
    "mapservice_event_to_stored_seconds",
    "Robot event time to stored in the history, per event",
    ["topic"],
    buckets=STORED_LATENCY_BUCKETS,
)
RECEIVED_TO_STORED = Histogram(
    "mapservice_received_to_stored_seconds",
    "Gateway receive time to stored in the history, per event",
    ["topic"],
    buckets=STORED_LATENCY_BUCKETS,
)
BATCH_WINDOW = Gauge(
    "mapservice_sink_batch_window_seconds",
    "How long the history consumer now collects a batch (batch_window.py)",
)
BATCH_EVENTS = Histogram(
    "mapservice_sink_batch_events",
    "Events per stored batch",
    buckets=(1, 10, 50, 100, 250, 500, 1000, 2000, 5000),
)


def observe_stored(topic: str, events: Sequence, now_ms: int) -> None:
    """Records each stored event's end-to-end latencies (clock skew can make the first
    negative: it is counted as 0)."""
    event_hist, receive_hist = EVENT_TO_STORED.labels(topic), RECEIVED_TO_STORED.labels(topic)
    for e in events:
        event_hist.observe(max(0.0, (now_ms - e.event_time_ms) / 1000))
        receive_hist.observe(max(0.0, (now_ms - e.receive_time_ms) / 1000))


async def store_values(
    sink: HistorySink,
    views: LiveViews | None,
    values_by_topic: Mapping[str, Sequence[bytes]],
    now_ms: int,
    clock_ms: Callable[[], int] = SystemClock().now_ms,
) -> list:
    """Decodes a batch, stores its events in one append, then feeds the live stream and
    the views; bad records become dead letters, and events older than the retention at
    `now_ms` are dropped (`HistorySink.unexpired`). Returns the stored events, whose derived
    pose views (`HistorySink.derive_until_done`) and conflicts and incidents (`LiveViews.write_found`)
    the caller writes before committing.

    One append for the whole batch, poses and chunks together: each append has a fixed
    cost (an insert per table, a snapshot check), and poses no longer wait behind the
    chunks' conflict detection to be stored. The derived pose views (schema v10) are left
    to the caller: they never delay the push, and feeding them several batches at once
    costs a fraction of feeding each batch (HistoryConsumer.views_seconds).

    `clock_ms` is the service's clock, read again once the insert returned: the events'
    times are on that clock, so on a simulated one the wall clock would make every
    latency metric wrong by the simulated offset.
    """
    good: list = []
    per_topic: dict[str, int] = {}
    by_topic: dict[str, list] = {}
    bad_by_topic = {}
    for topic, values in values_by_topic.items():
        decoded, bad = split_events(values, now_ms)
        events = sink.unexpired(topic, decoded, now_ms)
        good.extend(events)
        by_topic[topic] = events
        per_topic[topic] = len(events)
        if bad:
            bad_by_topic[topic] = bad
    if good:
        await sink.insert_until_done(sink.writer.append_events, good, per_topic)
        BATCH_EVENTS.observe(len(good))
        stored_ms = clock_ms()
        for topic, events in by_topic.items():
            observe_stored(topic, events, stored_ms)
        if sink.live is not None:
            sink.live.publish(good)
        if views is not None:
            await views.on_stored(good)  # conflicts, latest map, robots
    for topic, bad in bad_by_topic.items():
        log.warning("undecodable records on an event topic", topic=topic, count=len(bad))
        await sink.insert_until_done(sink.writer.append_dead_letters, bad, {topic: len(bad)})
    return good


class HistoryConsumer:
    """Owns one EventSource; every call to it runs on one thread of its own.

    The derived pose views are fed, the conflicts found written, and offsets committed,
    once per `views_seconds` of stored batches (at the latest; at once when a poll finds
    nothing, when `batch_size` events wait, on a rebalance and on stop): one insert into
    the pose views has a fixed cost several times a batch's own (BENCHMARKS.md, "pose
    views once a second"), which 5,000 robots cannot pay every 100 ms; the conflicts'
    insert has a fixed cost too (~10 ms, BENCHMARKS.md, "conflicts written once a second"). What that costs: the views (downsampled replay,
    timeline) and the conflicts may lag the history by `views_seconds`, and a crash
    re-delivers up to that much more (stored once: the history's identities absorb it).
    """

    def __init__(
        self,
        source: EventSource,
        sink: HistorySink,
        views: LiveViews | None,
        batch_size: int,
        batch_seconds: float,
        min_batch_seconds: float | None = None,
        quiet_batch_seconds: float | None = None,
        now_ms: Callable[[], int] = SystemClock().now_ms,
        monotonic: Callable[[], float] = time.monotonic,
        views_seconds: float = 1.0,
    ) -> None:
        self.source = source
        self.sink = sink
        self.views = views
        self.batch_size = batch_size
        self.batch_seconds = batch_seconds  # the longest window
        # The shortest window, taken while batches are stored quickly (batch_window.py);
        # None: always the longest.
        self.min_batch_seconds = batch_seconds if min_batch_seconds is None else min_batch_seconds
        # The longest a batch waits to gather a worthwhile size at a quiet plant's arrival
        # rate (batch_window.py); None: the longest window.
        self.quiet_batch_seconds = quiet_batch_seconds
        self.window_s = batch_seconds  # until stores were timed
        BATCH_WINDOW.set(self.window_s)
        self._store_s: float | None = None  # running store time per batch (smoothed)
        self._events_per_s: float | None = None  # running arrival rate (smoothed)
        self.now_ms = now_ms
        self.monotonic = monotonic
        self._last_poll_returned = -math.inf  # monotonic; the first poll takes what is queued
        self.assigned = False  # set by the source's assignment callback: rebuild the views
        self.has_partitions = False  # events flow only once the group assigned some
        self.joined = False  # readiness: the group took this replica in (maybe as a standby)
        # Liveness: a beat per turn and per store attempt (a retry during a ClickHouse
        # outage still beats); two minutes without one means the loop is dead or stuck.
        self.heartbeat = Heartbeat(max_age_s=120.0)
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="history-consumer")
        self.views_seconds = views_seconds
        self._underived: list = []  # stored events whose pose views are not derived yet
        self._underived_since: float | None = None  # monotonic, when the first of them was stored
        # Per partition, its latest stored record not yet committed.
        self._uncommitted: dict[tuple[str, int], SourceRecord] = {}

    def on_assigned(self, partitions: list[tuple[str, int]]) -> None:
        self.assigned = True
        self.joined = True
        self.has_partitions = self.has_partitions or bool(partitions)

    async def _call(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self._thread, fn, *args)

    async def start(self) -> None:
        await self._call(self.source.start)

    def poll_timeout(self) -> float:
        """How long the next poll may wait for records to fill a batch.

        A batch collects for the current window (`window_s`, between `min_batch_seconds`
        and `batch_seconds`: batch_window.py) from the return of the previous poll, and the
        time spent storing the previous batch counts toward it: its records waited in the
        consumer's queue meanwhile. So a slow insert is followed at once by the records
        that queued behind it instead of by another full wait, while fast inserts still
        make at most one batch per window (each insert has a fixed cost).
        """
        return max(0.0, self._last_poll_returned + self.window_s - self.monotonic())

    def _timed_store(self, store_s: float) -> None:
        """Sizes the next windows after a batch that took `store_s` to store (0 for an
        empty poll: when idle the window shrinks to what the recent arrival rate needs to
        fill a batch, so the first events after a pause wait least)."""
        self._store_s = smoothed(self._store_s, store_s)
        self.window_s = batch_window(
            self._store_s,
            self.min_batch_seconds,
            self.batch_seconds,
            self._events_per_s,
            self.quiet_batch_seconds,
        )
        BATCH_WINDOW.set(self.window_s)

    async def run_once(self) -> int:
        """One batch: poll, store, and (when due) derive the pose views and commit.
        Returns how many records it handled."""
        timeout = self.poll_timeout()
        records: list[SourceRecord] = await self._call(self.source.poll, self.batch_size, timeout)
        previous, self._last_poll_returned = self._last_poll_returned, self.monotonic()
        if records and math.isfinite(previous) and self._last_poll_returned > previous:
            # Gathered since the previous poll returned (an idle poll leaves the rate be:
            # a quiet spell is no reason to store the next events sooner).
            rate = len(records) / (self._last_poll_returned - previous)
            self._events_per_s = smoothed(self._events_per_s, rate)
        if self.assigned:
            self.assigned = False
            # The group changed: the pose views of what this replica stored are derived
            # first. The source commits no offset read before the change (its partition
            # may be another's now), so those records are delivered again: stored once.
            await self._in_group(self.settle())
            if self.views is not None:
                # New partitions: rebuild the views from the history before their events
                # (which may repeat what is stored) are applied.
                await self._in_group(self.views.rebuild())
        if not records:
            if self.views is not None and timeout >= min(CAUGHT_UP_WAIT_S, self.min_batch_seconds):
                # waited and found nothing: not behind the stream (a poll that may not wait,
                # after a long store, can come back empty with a backlog still to fetch)
                self.views.clock.caught_up()
            await self._in_group(self.settle())  # idle: the views catch up at once
            self._timed_store(0.0)
            return 0
        stored = await self._in_group(self._store_until_done(records))
        # The window is sized by the batch's own store time; the views' insert, once per
        # views_seconds, would make it jump.
        self._timed_store(self.monotonic() - self._last_poll_returned)
        self._underived.extend(stored)
        for r in records:
            self._uncommitted[(r.topic, r.partition)] = r
        if self._underived_since is None:
            self._underived_since = self.monotonic()
        if (
            self.monotonic() - self._underived_since >= self.views_seconds
            or len(self._underived) >= self.batch_size
        ):
            await self._in_group(self.settle())
        return len(records)

    async def _store_until_done(self, records: list[SourceRecord]) -> list:
        # Moving on would let the next commit cover this batch: retry it instead.
        async for attempt in until_done("history batch", 0.5, records=len(records)):
            with attempt:
                self.heartbeat.beat()
                stored = await self._store(records)
        return stored

    async def _in_group(self, work: Awaitable[T]) -> T:
        """`work`, while the source keeps this member in its group every
        STAY_IN_GROUP_EVERY_S: a ClickHouse outage retried for a minute, or a rebuild
        longer than the poll interval, would else make it leave the group, and the
        rejoin's rebuild cost as much again (a loop while rebuilds outlast the interval).
        The source's calls run on the consumer's thread, one at a time with its polls."""
        task = asyncio.ensure_future(work)
        while True:
            done, _ = await asyncio.wait({task}, timeout=STAY_IN_GROUP_EVERY_S)
            if done:
                return task.result()
            try:
                await self._call(self.source.stay_in_group)
            except BaseException:
                task.cancel()
                raise

    async def settle(self) -> None:
        """Derives the pose views of the stored events and writes the conflicts found in
        them, then commits their offsets."""
        if self._underived:
            await self.sink.derive_until_done(self._underived)
            self._underived = []
        if self.views is not None:
            await self.views.write_found_until_done()
        self._underived_since = None
        if self._uncommitted:
            records, self._uncommitted = list(self._uncommitted.values()), {}
            if not await self._call(self.source.commit, records):
                COMMIT_FAILURES.inc()

    async def _store(self, records: list[SourceRecord]) -> list:
        by_topic: dict[str, list[bytes]] = {}
        for r in records:
            by_topic.setdefault(r.topic, []).append(r.value)
        return await store_values(self.sink, self.views, by_topic, self.now_ms(), self.now_ms)

    async def _settle_once(self) -> None:
        """On stop: one try, no retries (an unreachable store must not hold the stop up;
        what is not committed is delivered again)."""
        try:
            if self._underived:
                await self.sink.run(self.sink.writer.derive_views, self._underived)
                self._underived = []
            if self.views is not None:
                await self.views.store_thread.run(self.views.write_found)
            await self.settle()
        except Exception as exc:  # noqa: BLE001 - anything the store raises; logged, re-delivered
            log.warning(
                "could not derive the pose views or write the conflicts on stop; "
                "their events will be delivered again",
                events=len(self._underived),
                error=str(exc),
            )

    async def run(self, stopping: asyncio.Event) -> None:
        await self.start()
        try:
            while not stopping.is_set():
                self.heartbeat.beat()
                await self.run_once()
            await self._settle_once()
        finally:
            await self._call(self.source.close)
            self._thread.shutdown(wait=False)


class HistoryConsumerService(mode.Service):
    """Runs a HistoryConsumer for as long as the faust app runs."""

    def __init__(self, consumer: HistoryConsumer, **kwargs) -> None:
        super().__init__(**kwargs)
        self.consumer = consumer
        self._stopping = asyncio.Event()

    @mode.Service.task
    async def _consume(self) -> None:
        await self.consumer.run(self._stopping)

    async def on_stop(self) -> None:
        self._stopping.set()
