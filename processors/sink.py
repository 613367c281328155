"""The history sink: the one thread that talks to the store, and the pure part (raw Kafka
values to what the store appends)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor

import msgspec
from prometheus_client import Counter, Histogram

from mapservice.core.events import DeadLetter, Envelope, decode, decode_dead_letter
from mapservice.core.ports import HistoryStore, LiveFeed
from mapservice.runtime.retry import until_done

STORED = Counter("mapservice_sink_events_total", "Events appended to the history", ["topic"])
INSERT_SECONDS = Histogram("mapservice_sink_insert_seconds", "Duration of one history insert",
                           buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5))
DERIVE_SECONDS = Histogram("mapservice_sink_derive_views_seconds",
                           "Duration of one insert into the derived pose views (many batches)",
                           buckets=(0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5))
INSERT_FAILURES = Counter("mapservice_sink_insert_failures_total", "Inserts that failed and were retried")


class HistorySink:
    """Owns the store and the one thread that talks to it."""

    def __init__(self, store: HistoryStore, live: LiveFeed | None = None) -> None:
        self.store = store
        self.live = live
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="history")
        self.consumer = None  # the HistoryConsumer feeding it, once build_app made one

    async def run(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)

    async def insert_until_done(self, fn, batch, counts: Mapping[str, int]) -> None:
        """Stores `batch` with `fn`, retrying until it is in; then counts it as stored,
        per topic (`counts`: how many of the batch came from each topic)."""
        # Retried, never skipped: acknowledging a batch that is not stored would lose it.
        async for attempt in until_done("history insert", 0.2, INSERT_FAILURES.inc,
                                        topics=sorted(counts), batch=len(batch)):
            with attempt:
                started = time.monotonic()
                await self.run(fn, batch)
        INSERT_SECONDS.observe(time.monotonic() - started)
        for topic, count in counts.items():
            STORED.labels(topic).inc(count)

    async def derive_until_done(self, batch) -> None:
        """Brings the derived pose views up to a stored `batch`, retrying until it is done
        (its offsets are committed after this: a batch whose views are missing is never
        acknowledged)."""
        async for attempt in until_done("history views", 0.2, INSERT_FAILURES.inc, batch=len(batch)):
            with attempt:
                started = time.monotonic()
                await self.run(self.store.derive_views, batch)
        DERIVE_SECONDS.observe(time.monotonic() - started)


def split_events(values: Iterable[bytes], now_ms: int) -> tuple[list[Envelope], list[DeadLetter]]:
    """Decodes envelopes; a record that is not one becomes a dead letter, not a crash."""
    events: list[Envelope] = []
    bad: list[DeadLetter] = []
    for value in values:
        try:
            events.append(decode(value))
        except (msgspec.DecodeError, TypeError, UnicodeDecodeError) as exc:
            bad.append(DeadLetter(reason="undecodable_event", detail=str(exc)[:500],
                                  mqtt_topic="", payload=value or b"", receive_time_ms=now_ms,
                                  gateway="processors"))
    return events, bad


def decode_dead_letters(values: Iterable[bytes], now_ms: int) -> list[DeadLetter]:
    out = []
    for value in values:
        try:
            out.append(decode_dead_letter(value))
        except (msgspec.DecodeError, TypeError, UnicodeDecodeError) as exc:
            out.append(DeadLetter(reason="undecodable_dead_letter", detail=str(exc)[:500],
                                  mqtt_topic="", payload=value or b"", receive_time_ms=now_ms,
                                  gateway="processors"))
    return out
