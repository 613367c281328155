"""The processors' live views over a MemoryStore, without brokers: advertisements on
changes only, rebuilt from the history, conflicts recorded, advertiser trouble contained."""

from __future__ import annotations

import asyncio

import pytest
from prometheus_client import REGISTRY

from mapservice.processors.history_consumer import HistoryConsumer
from mapservice.processors.sink import HistorySink
from mapservice.processors.views import LiveViews
from mapservice.settings import Settings
from mapservice.testing.memory_source import MemorySource
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import NOW_MS, chunk_event, pose_event
from tests.processors.history_consumer_kit import live_views


class FakeAdvertiser:
    def __init__(self, fail: bool = False) -> None:
        self.sent: list[dict] = []
        self.fail = fail

    def start(self) -> None:
        pass

    def publish(self, payload: dict) -> bool:
        if self.fail:
            raise ConnectionError("broker gone")
        self.sent.append(payload)
        return True

    def stop(self) -> None:
        pass


@pytest.fixture
def sink():
    s = HistorySink(MemoryStore())
    yield s
    s.thread.close()


def _views(sink, advertiser, now=NOW_MS, **settings) -> LiveViews:
    return live_views(
        Settings(public_base_url="http://api:8080", **settings),
        sink.writer,
        advertiser,
        sink.thread,
        now_ms=lambda: now,
    )


def _store_and_view(views: LiveViews, sink: HistorySink, events) -> None:
    sink.writer.append(events)
    asyncio.run(views.on_stored(events))
    views.flush()


def test_changes_are_advertised_once_and_older_writes_never(sink) -> None:
    """A newer write is advertised; an older one and a re-delivery are not."""
    ads = FakeAdvertiser()
    views = _views(sink, ads)
    views.load()
    _store_and_view(views, sink, [chunk_event("a", NOW_MS, 1, 2)])
    _store_and_view(
        views,
        sink,
        [
            chunk_event("b", NOW_MS - 1000, 1, 2, bytes([7]) * 10_000),
            chunk_event("a", NOW_MS, 1, 2),
        ],
    )
    _store_and_view(views, sink, [chunk_event("b", NOW_MS + 1000, 1, 2)])
    assert [(a["robotId"], a["id"]) for a in ads.sent] == [
        ("a", "row:1_column:2_2026-11-21T10:00:00"),
        ("b", "row:1_column:2_2026-11-21T10:00:01"),
    ]
    assert ads.sent[0]["chunkUrl"].startswith("http://api:8080/api/chunk-service/chunks/id/")


def test_rebuilt_views_continue_where_the_history_is(sink) -> None:
    """After a restart the view comes from the store: stored writes are not re-advertised,
    older ones still lose, newer ones are advertised."""
    sink.writer.append([chunk_event("a", NOW_MS, 0, 0), pose_event("r1", NOW_MS)])
    ads = FakeAdvertiser()
    views = _views(sink, ads)
    views.load()
    assert set(views.latest) == {(0, 0)} and set(views.robots) == {"r1"}
    _store_and_view(
        views, sink, [chunk_event("a", NOW_MS, 0, 0), chunk_event("b", NOW_MS - 5, 0, 0)]
    )
    assert ads.sent == []
    _store_and_view(views, sink, [chunk_event("b", NOW_MS + 5, 0, 0)])
    assert [a["robotId"] for a in ads.sent] == ["b"]


def test_conflicts_found_per_batch_are_written_together(sink) -> None:
    """Different content from two robots within the window becomes a conflict row, stored
    by write_conflicts (not by the batch), which then has nothing left to write."""
    views = _views(sink, None, conflict_window_s=10)
    views.load()
    _store_and_view(views, sink, [chunk_event("a", NOW_MS, 4, 4)])
    _store_and_view(
        views,
        sink,
        [
            chunk_event("b", NOW_MS + 9_000, 4, 4, bytes([1]) * 10_000),
            chunk_event("c", NOW_MS + 30_000, 4, 4, bytes([2]) * 10_000),
        ],
    )
    assert sink.writer.conflicts(NOW_MS, NOW_MS + 60_000) == []
    assert views.write_conflicts() == 1
    rows = sink.writer.conflicts(NOW_MS, NOW_MS + 60_000)
    assert [(c.robot_a, c.robot_b, c.ts_ms - NOW_MS) for c in rows] == [("a", "b", 9_000)]
    assert views.write_conflicts() == 0


def test_a_conflict_found_again_with_a_later_a_is_written_once_with_it(sink) -> None:
    """Two batches move one conflict's A to a later write before the write: one row, the later A."""
    views = _views(sink, None, conflict_window_s=10)
    views.load()
    _store_and_view(
        views,
        sink,
        [
            chunk_event("a", NOW_MS, 4, 4),
            chunk_event("c", NOW_MS + 5_000, 4, 4, bytes([2]) * 10_000),
        ],
    )
    _store_and_view(views, sink, [chunk_event("b", NOW_MS + 2_000, 4, 4, bytes([1]) * 10_000)])
    assert views.write_conflicts() == 2
    rows = sink.writer.conflicts(NOW_MS, NOW_MS + 60_000)
    assert [(c.robot_a, c.robot_b, c.ts_ms - NOW_MS) for c in rows] == [
        ("a", "b", 2_000),
        ("b", "c", 5_000),
    ]


def test_each_batch_conflict_check_and_each_write_are_timed(sink) -> None:
    """A batch with chunks is observed in the check histogram; only a write with rows in the write one."""
    views = _views(sink, None)
    views.load()
    checks = REGISTRY.get_sample_value("mapservice_conflicts_check_seconds_count") or 0
    writes = REGISTRY.get_sample_value("mapservice_conflicts_write_seconds_count") or 0
    _store_and_view(views, sink, [chunk_event("a", NOW_MS, 4, 4)])
    _store_and_view(views, sink, [pose_event("r1", NOW_MS)])
    _store_and_view(views, sink, [chunk_event("b", NOW_MS + 1, 4, 4, bytes([1]) * 10_000)])
    views.write_conflicts()
    views.write_conflicts()
    assert REGISTRY.get_sample_value("mapservice_conflicts_check_seconds_count") == checks + 2
    assert REGISTRY.get_sample_value("mapservice_conflicts_write_seconds_count") == writes + 1


def test_a_failing_advertiser_does_not_stop_the_sink(sink) -> None:
    """An advertiser that raises is logged; the views still change and conflicts are stored."""
    views = _views(sink, FakeAdvertiser(fail=True))
    views.load()
    _store_and_view(views, sink, [chunk_event("a", NOW_MS, 0, 0)])
    assert (0, 0) in views.latest


def test_presence_transitions(sink) -> None:
    """Robots go online when heard from and offline after robot_offline_after_s of silence."""
    now = [NOW_MS]
    views = live_views(
        Settings(robot_offline_after_s=10), sink.writer, None, sink.thread, now_ms=lambda: now[0]
    )
    asyncio.run(views.on_stored([pose_event("r1", NOW_MS, receive_lag_ms=0)]))
    assert views.check_presence() == ({"r1"}, set())
    now[0] += 10_001
    assert views.check_presence() == (set(), {"r1"})


def test_an_assignment_rebuilds_the_views_and_starts_the_advertiser(sink) -> None:
    """A partition assignment to the history consumer rebuilds the views on the store thread
    and starts the advertiser (the faust app's shutdown stopping it: test_composition.py)."""

    class Recorder(FakeAdvertiser):
        calls: list[str] = []

        def start(self) -> None:
            self.calls.append("start")

    sink.writer.append([chunk_event("a", NOW_MS, 2, 3)])
    adv = Recorder()
    views = live_views(Settings(), sink.writer, adv, sink.thread)
    assert views.latest == {}

    consumer = HistoryConsumer(MemorySource(), sink, views, batch_size=10, batch_seconds=0.01)

    async def lifecycle() -> None:
        await consumer.start()
        consumer.on_assigned([("mapservice.chunk-events.v1", 0)])
        await consumer.run_once()

    asyncio.run(lifecycle())
    assert set(views.latest) == {(2, 3)} and adv.calls == ["start"]


def test_advertisements_beyond_the_backlog_bound_are_dropped(sink, monkeypatch) -> None:
    """With the encoding backlog full, a change is dropped (counted), not queued or awaited."""
    import mapservice.processors.advertising as advertising

    monkeypatch.setattr(advertising, "MAX_PENDING_ADS", 0)
    ads = FakeAdvertiser()
    views = _views(sink, ads)
    views.load()
    _store_and_view(views, sink, [chunk_event("a", NOW_MS, 0, 0)])
    assert ads.sent == [] and (0, 0) in views.latest


def test_a_failed_rebuild_is_retried_before_the_next_batch_is_applied(sink, monkeypatch) -> None:
    """If rebuilding at assignment fails, the app keeps running and the next stored batch
    rebuilds first, so an older write still cannot win."""
    sink.writer.append([chunk_event("a", NOW_MS, 0, 0)])
    ads = FakeAdvertiser()
    views = live_views(Settings(), sink.writer, ads, sink.thread)
    real_map_at = sink.writer.map_at
    monkeypatch.setattr(sink.writer, "map_at", lambda at: (_ for _ in ()).throw(OSError("down")))
    consumer = HistoryConsumer(MemorySource(), sink, views, batch_size=10, batch_seconds=0.01)
    consumer.on_assigned([("mapservice.chunk-events.v1", 0)])
    asyncio.run(consumer.run_once())
    assert not views.loaded
    monkeypatch.setattr(sink.writer, "map_at", real_map_at)
    _store_and_view(views, sink, [chunk_event("b", NOW_MS - 1, 0, 0)])
    assert views.loaded and ads.sent == [] and views.latest[(0, 0)].robot_id == "a"
