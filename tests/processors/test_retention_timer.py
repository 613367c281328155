"""The processors' snapshot timer on the service's clock: repairs, snapshots and the
retention step, as production runs them (processors/app.py `snapshot_timer`), through
three retention periods of a simulated clock; the floor written once on the first day
stays whole at every instant of the retention."""

from __future__ import annotations

import asyncio
import datetime as dt
import time

import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.clock import ManualClock, SimulatedClock, clock_from_settings
from mapservice.core.timetravel import fold_map
from mapservice.processors.app import snapshot_tick_s, snapshot_timer
from mapservice.processors.sink import HistorySink
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event, pose_event

DAY = 86_400_000
T0 = int(dt.datetime(2026, 3, 1, tzinfo=dt.UTC).timestamp() * 1000)


def _store(kind: str, tmp_path):
    if kind == "memory":
        return MemoryStore(retention_days=2)
    s = ClickHouseStore(
        f"chdb://{tmp_path / 'ch'}",
        database="timer",
        retention_days=2,
        snapshot_every_ms=6 * 3_600_000,
    )
    s.migrate()
    return s


@pytest.mark.parametrize("kind", ["memory", "clickhouse"])
def test_the_snapshot_timer_keeps_the_floor_through_three_retention_periods(kind, tmp_path) -> None:
    store = _store(kind, tmp_path)
    sink = HistorySink(store)
    clock = ManualClock(T0)
    tick = snapshot_timer(sink, store, store, clock.now_ms, grace_ms=60_000)
    floor = [
        chunk_event("mapper", T0 + 1, r, c, bytes([r * 10 + c]) * 10_000)
        for r in range(3)
        for c in range(3)
    ]
    store.append(floor)
    written = list(floor)

    async def run() -> None:
        for hour in range(1, 8 * 24 + 1):  # 8 days: retention 2 days, four periods
            moved = chunk_event(
                "amr", T0 + hour * 3_600_000 - 500, 1, 1, bytes([hour % 256]) * 10_000
            )
            store.append([moved, pose_event("amr", T0 + hour * 3_600_000 - 400)])
            written.append(moved)
            clock.advance(3_600_000)
            await tick()

    asyncio.run(run())
    sink.thread.close()
    now = clock.now_ms()
    rows = [
        type(
            "W",
            (),
            {
                "row": e.payload.row,
                "column": e.payload.column,
                "ts_ms": e.event_time_ms,
                "robot_id": e.robot_id,
                "content_hash": e.payload.content_hash.hex(),
            },
        )()
        for e in written
    ]
    for t in range(now - 2 * DAY, now + 1, 5 * 3_600_000):
        want = {k: v.content_hash for k, v in fold_map(rows, t).items()}
        got = {(c.row, c.column): c.content_hash for c in store.map_at(t)}
        assert got == want, f"map at {t} ({(now - t) / DAY:.2f} days ago)"
        assert len(store.chunk_contents([bytes.fromhex(h) for h in want.values()])) == len(
            set(want.values())
        )
    # The history before the retention's kept days is gone.
    assert not store.chunk_events(0, now - 3 * DAY)
    store.close()


def test_simulated_clock_runs_at_its_rate_from_its_start() -> None:
    clock = SimulatedClock(T0, rate=1000.0, origin_ms=time.time_ns() // 1_000_000 - 2000)
    assert 1_999_000 <= clock.now_ms() - T0 <= 2_500_000


def test_clock_from_settings_is_the_wall_clock_by_default_and_simulated_when_set() -> None:
    assert abs(clock_from_settings(Settings()).now_ms() - time.time_ns() // 1_000_000) < 1000
    simulated = clock_from_settings(
        Settings(
            clock_start="2026-03-01T00:00:00Z",
            clock_rate=3600,
            clock_origin=str(time.time_ns() // 1_000_000),
        )
    )
    assert 0 <= simulated.now_ms() - T0 < 3_600_000 * 5
    with pytest.raises(ValueError, match="MAPSERVICE_CLOCK_START"):
        clock_from_settings(Settings(clock_start="yesterday"))


def test_the_snapshot_timer_ticks_faster_on_a_faster_clock() -> None:
    assert snapshot_tick_s(Settings()) == 30.0
    assert snapshot_tick_s(Settings(clock_rate=60)) == pytest.approx(0.5)
    assert snapshot_tick_s(Settings(clock_rate=6000)) == pytest.approx(0.2)  # at most 5 a second
    assert snapshot_tick_s(Settings(snapshot_every_s=3600, clock_rate=30)) == pytest.approx(1.0)


def test_the_snapshot_timers_period_can_be_set_outright() -> None:
    for tick in (0.2, 2.0, 45.0):
        assert snapshot_tick_s(Settings(snapshot_tick_s=tick)) == tick
        assert snapshot_tick_s(Settings(snapshot_tick_s=tick, clock_rate=6000)) == tick
    with pytest.raises(ValueError, match="snapshot_tick_s"):
        Settings(snapshot_tick_s=0.05)  # more than five ticks a second: refused
