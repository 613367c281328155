"""The analysts' own bounded pool: at most N statements run, M wait, the rest get "too many
queries" at once (HTTP 503 with Retry-After), and none of it runs on anyio's threads."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
from mapservice.sql.query_gate import QueryGate, TooManyQueries
from mapservice.sql.read_only import ReadOnlyLimits

from .serving import ServedApp


def test_the_gate_runs_at_most_n_queues_m_and_refuses_the_rest() -> None:
    gate = QueryGate(concurrent=2, queued=1, queue_timeout_s=10)
    release = threading.Event()
    running: list[str] = []

    def work() -> str:
        running.append(threading.current_thread().name)
        release.wait(10)
        return "done"

    async def scenario():
        tasks = [asyncio.create_task(gate.run(work)) for _ in range(3)]
        await asyncio.sleep(0.2)
        assert len(running) == 2 and gate.admitted == 3  # two run, one waits
        with pytest.raises(TooManyQueries, match="Too many queries") as refused:
            await gate.run(work)  # the fourth: refused at once, never run
        assert refused.value.code == 202 and refused.value.http_status == 503
        release.set()
        assert await asyncio.gather(*tasks) == ["done"] * 3
        assert gate.admitted == 0

    asyncio.run(scenario())
    assert len(running) == 3 and all(name.startswith("analyst-sql") for name in running)
    gate.close()


def test_a_waiting_statement_gives_up_after_the_queue_timeout() -> None:
    gate = QueryGate(concurrent=1, queued=5, queue_timeout_s=0.3)
    release = threading.Event()

    async def scenario():
        first = asyncio.create_task(gate.run(release.wait, 10))
        await asyncio.sleep(0.1)
        with pytest.raises(TooManyQueries, match=r"waited 0.3 s"):
            await gate.run(time.sleep, 0)
        release.set()
        assert await first is True
        assert gate.admitted == 0

    asyncio.run(scenario())
    gate.close()


def test_an_abandoned_statement_keeps_its_slot_until_it_ends() -> None:
    """The caller gone (client disconnected) does not free the thread the statement holds."""
    gate = QueryGate(concurrent=1, queued=0, queue_timeout_s=5)
    release = threading.Event()

    async def scenario():
        task = asyncio.create_task(gate.run(release.wait, 10))
        await asyncio.sleep(0.1)
        task.cancel()
        await asyncio.sleep(0.05)
        with pytest.raises(TooManyQueries):
            await gate.run(time.sleep, 0)
        release.set()
        await asyncio.sleep(0.1)
        assert await gate.run(lambda: 7) == 7

    asyncio.run(scenario())
    gate.close()


class ThreadRecordingEngine:
    """The chDB engine, noting the thread each statement runs on."""

    def __init__(self, engine):
        self.engine, self.threads = engine, []

    def execute(self, request):
        self.threads.append(threading.current_thread().name)
        return self.engine.execute(request)

    def __getattr__(self, name):
        return getattr(self.engine, name)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    engine = ChdbEngine(
        tmp_path_factory.mktemp("gate") / "ch", read_only_settings=ReadOnlyLimits().settings()
    )
    recording = ThreadRecordingEngine(engine)
    app = clickhouse_http_app(
        recording,
        [SqlUser("analyst", "a-pw", read_only=True)],
        read_only_gate=QueryGate(concurrent=1, queued=1, queue_timeout_s=20),
    )
    with ServedApp(app) as served:
        yield served.url, recording
    engine.close()


def test_beyond_the_pool_and_queue_analysts_get_503_too_many_queries(served) -> None:
    """Six concurrent `SELECT sleep(3)` on a pool of one with a queue of one: two answer,
    four get 503 at once with Retry-After and ClickHouse's TOO_MANY_SIMULTANEOUS_QUERIES;
    every statement ran on the analysts' threads."""
    url, recording = served

    def ask(_):
        started = time.monotonic()
        reply = httpx.post(url, content=b"SELECT sleep(3)", auth=("analyst", "a-pw"), timeout=30)
        return reply, time.monotonic() - started

    with ThreadPoolExecutor(6) as pool:
        replies = list(pool.map(ask, range(6)))
    ok = [r for r, _ in replies if r.status_code == 200]
    busy = [(r, s) for r, s in replies if r.status_code == 503]
    assert len(ok) == 2 and len(busy) == 4, [r.text for r, _ in replies]
    for reply, seconds in busy:
        assert reply.headers["X-ClickHouse-Exception-Code"] == "202"
        assert int(reply.headers["Retry-After"]) >= 1
        assert "Too many queries" in reply.text and "TOO_MANY_SIMULTANEOUS_QUERIES" in reply.text
        assert seconds < 2.5  # refused at once, not after the 3 s the first one runs
    assert recording.threads and all(t.startswith("analyst-sql") for t in recording.threads)


def test_each_statement_gets_its_share_of_the_analysts_memory(tmp_path) -> None:
    """max_memory_usage per statement = min(per statement, total / concurrent), so the
    statements that may run at once stay within the total."""
    from mapservice.settings import Settings
    from mapservice.sql.credentials import analyst_limits

    def memory(**kw) -> int:
        return int(analyst_limits(Settings(data_dir=tmp_path, **kw)).settings()["max_memory_usage"])

    assert memory() == 1024**3  # 2 GiB total, 2 at a time
    assert memory(analyst_max_concurrent_queries=4) == 512 * 1024**2
    assert memory(analyst_max_memory_bytes=256 * 1024**2) == 256 * 1024**2
    assert memory(analyst_max_memory_total_bytes=8 * 1024**3) == 2 * 1024**3
