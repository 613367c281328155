"""What the history consumer's tests share: the topics, a fixed instant, a store that is
briefly away, a hand-driven clock, and a consumer drained to the end of its source."""

from __future__ import annotations

import asyncio

from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import HistorySink
from mapservice.processors.store_thread import StoreThread
from mapservice.processors.views import Advertiser, LiveViews
from mapservice.settings import Settings
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000
POSES, CHUNKS = "poses", "chunks"


class FlakyStore(MemoryStore):
    """Fails the first `failures` appends, as a ClickHouse that is briefly away would."""

    def __init__(self, failures: int) -> None:
        super().__init__()
        self.failures = failures
        self.attempts = 0

    def append_events(self, events) -> None:
        self.attempts += 1
        if self.failures:
            self.failures -= 1
            raise ConnectionError("clickhouse away")
        super().append_events(events)


def live_views(
    settings: Settings,
    store: MemoryStore,
    advertiser: Advertiser | None,
    thread: StoreThread,
    now_ms=None,
    live=None,
) -> LiveViews:
    """Live views whose every role is the test's one in-memory store (`live`: where the
    incidents are announced)."""
    clock = {} if now_ms is None else {"now_ms": now_ms}
    return LiveViews(
        settings,
        history=store,
        annotations=store,
        conflicts=store,
        incidents=store,
        commands=store,
        vda=store,
        writer=store,
        advertiser=advertiser,
        store_thread=thread,
        live=live,
        **clock,
    )


def consumer_for(store: MemoryStore, source: MemorySource, batch: int = 100) -> HistoryConsumer:
    return HistoryConsumer(
        source, HistorySink(store), None, batch_size=batch, batch_seconds=0.01, now_ms=lambda: NOW
    )


def drain(consumer: HistoryConsumer) -> None:
    async def go() -> None:
        await consumer.start()
        while await consumer.run_once():
            pass

    asyncio.run(go())


class Clock:
    """A monotonic clock the test moves by hand (`clock.t += seconds`)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t
