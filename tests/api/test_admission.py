"""Admission control (api/admission.py): the probes answer while every read is stuck, each
pool refuses beyond its workers and queue with 503 and Retry-After, one caller cannot take
a pool alone (429), and /clickhouse and the WebSocket are rate-limited like every route."""

from __future__ import annotations

import asyncio
import base64
import socket
import threading
import time

import httpx
import pytest
from fastapi.testclient import TestClient
from prometheus_client import REGISTRY
from starlette.testclient import WebSocketDenialResponse

from mapservice.api.app import create_app
from mapservice.api.live_hub import LiveHub
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.api.test_slow_clients import served

LIVE_URL = "ws://localhost/api/v1/live"


class StuckStore(MemoryStore):
    """robots_at waits until released: a read as slow as a costly one, without the CPU."""

    def __init__(self) -> None:
        super().__init__()
        self.release = threading.Event()
        self.entered = 0

    def robots_at(self, at_ms: int, after=None, limit=None):
        self.entered += 1
        self.release.wait(30)
        return super().robots_at(at_ms, after=after, limit=limit)


def client_at(app, address: str) -> httpx.AsyncClient:
    """A client from its own address: anonymous callers are told apart by address."""
    return httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app, client=(address, 40000)), base_url="http://127.0.0.1"
    )


async def _get(app, address: str, path: str) -> httpx.Response:
    async with client_at(app, address) as client:
        return await client.get(path, timeout=60)


def test_probes_answer_within_a_second_under_60_stuck_reads() -> None:
    """60 readers (each from its own address) on a read that does not return: the reads'
    pool serves 8 and queues 32, the other 20 get 503 with Retry-After at once, and
    /healthz and /readyz answer within a second all along. Without the pools the 60 reads
    took anyio's 40 threads and the (then sync) probes waited behind them."""
    store = StuckStore()
    settings = Settings(api_read_workers=8, api_read_queue=32, api_queue_wait_s=30)
    app = create_app(settings, store, {"clickhouse": lambda: True})

    async def scenario():
        reads = [
            asyncio.create_task(_get(app, f"10.0.{i // 200}.{i % 200 + 1}", "/api/v1/robots"))
            for i in range(60)
        ]
        await asyncio.sleep(1.0)
        probe_times = []
        for path in ("/healthz", "/readyz", "/healthz", "/readyz"):
            started = time.monotonic()
            reply = await asyncio.wait_for(_get(app, "10.9.9.9", path), timeout=5)
            probe_times.append(time.monotonic() - started)
            assert reply.status_code == 200, reply.text
        refused = [t.result() for t in reads if t.done()]
        store.release.set()
        done = await asyncio.gather(*reads)
        return probe_times, refused, done

    probe_times, refused, done = asyncio.run(scenario())
    assert max(probe_times) < 1.0, probe_times
    assert len(refused) == 20 and {r.status_code for r in refused} == {503}
    for reply in refused:
        assert reply.headers["retry-after"].isdigit()
        assert "MAPSERVICE_API_READ_WORKERS" in reply.json()["detail"]
    assert sum(r.status_code == 200 for r in done) == 40
    assert store.entered == 40  # never more than the pool at once, the queue after them


def test_a_queued_read_is_refused_after_the_queue_wait() -> None:
    """One worker busy, one request queued: after MAPSERVICE_API_QUEUE_WAIT_S a 503 says so."""
    store = StuckStore()
    app = create_app(Settings(api_read_workers=1, api_read_queue=1, api_queue_wait_s=0.3), store)

    async def scenario():
        stuck = asyncio.create_task(_get(app, "10.0.0.1", "/api/v1/robots"))
        await asyncio.sleep(0.2)
        queued = await _get(app, "10.0.0.2", "/api/v1/robots")
        store.release.set()
        await stuck
        return queued

    queued = asyncio.run(scenario())
    assert queued.status_code == 503 and "MAPSERVICE_API_QUEUE_WAIT_S" in queued.json()["detail"]
    assert "retry-after" in queued.headers


def test_one_caller_cannot_take_the_pool_alone() -> None:
    """An address with MAPSERVICE_API_CALLER_CONCURRENCY reads running waits its turn for
    one more (no longer refused); another address is served at once meanwhile, and the
    waiting one once one of its own is done."""
    store = StuckStore()
    app = create_app(Settings(api_caller_concurrency=2, api_read_workers=8), store)

    async def entered(count: int) -> None:
        # Waited for, not slept on: a loaded machine may take seconds to start a thread.
        deadline = time.monotonic() + 30
        while store.entered < count:
            assert time.monotonic() < deadline, (store.entered, count)
            await asyncio.sleep(0.02)

    async def scenario():
        mine = [asyncio.create_task(_get(app, "10.0.0.1", "/api/v1/robots")) for _ in range(2)]
        await entered(2)
        third = asyncio.create_task(_get(app, "10.0.0.1", "/api/v1/robots"))
        other = asyncio.create_task(_get(app, "10.0.0.2", "/api/v1/robots"))
        await entered(3)  # the other's, served at once
        await asyncio.sleep(0.3)
        reads = store.entered  # the two of 10.0.0.1 and the other's, not the third
        store.release.set()
        return reads, await third, await other, await asyncio.gather(*mine)

    reads, third, other, mine = asyncio.run(scenario())
    assert reads == 3
    assert third.status_code == 200 and other.status_code == 200
    assert all(r.status_code == 200 for r in mine)


def test_a_caller_over_its_queue_share_gets_429_with_retry_after() -> None:
    """Beyond MAPSERVICE_API_CALLER_QUEUE waiting reads of one address, one more is 429 at
    once with Retry-After; another address still gets a place in the queue."""
    store = StuckStore()
    settings = Settings(api_read_workers=1, api_read_queue=8, api_caller_queue=2)
    app = create_app(settings, store)

    async def scenario():
        mine = [asyncio.create_task(_get(app, "10.0.0.1", "/api/v1/robots")) for _ in range(3)]
        await asyncio.sleep(0.3)
        over = await _get(app, "10.0.0.1", "/api/v1/robots")
        other = asyncio.create_task(_get(app, "10.0.0.2", "/api/v1/robots"))
        await asyncio.sleep(0.2)
        store.release.set()
        return over, await other, await asyncio.gather(*mine)

    over, other, mine = asyncio.run(scenario())
    assert over.status_code == 429 and "MAPSERVICE_API_CALLER_QUEUE" in over.json()["detail"]
    assert over.headers["retry-after"].isdigit()
    assert other.status_code == 200 and [r.status_code for r in mine] == [200] * 3


class OrderedStore(StuckStore):
    """Records which `at` each read asked for, in the order they ran, as ms after `base`
    (an hour ago: within the retention, as `at` must be)."""

    def __init__(self) -> None:
        super().__init__()
        self.base = time.time_ns() // 1_000_000 - 3_600_000
        self.order: list[int] = []

    def robots_at(self, at_ms: int, after=None, limit=None):
        self.order.append(at_ms - self.base)
        return super().robots_at(at_ms, after=after, limit=limit)

    def path(self, offset: int) -> str:
        return f"/api/v1/robots?at={self.base + offset}"


def test_two_sessions_of_one_address_take_turns() -> None:
    """A tab with twelve reads queued and a second tab of the same address asking three:
    the second tab's reads run between the first's (turns per X-Mapservice-Session), not
    after all twelve; a client naming a session per request gains nothing over one that
    names none (they share the address's turns with the other address)."""
    store = OrderedStore()
    app = create_app(Settings(api_read_workers=1, api_read_queue=32), store)

    async def get(address: str, at: int, session: str):
        return await _session_get(app, address, store.path(at), session)

    async def scenario():
        first = [asyncio.create_task(get("10.0.0.1", 100 + i, "tab1")) for i in range(12)]
        await asyncio.sleep(0.3)
        second = [asyncio.create_task(get("10.0.0.1", 200 + i, "tab2")) for i in range(3)]
        await asyncio.sleep(0.3)
        store.release.set()
        return await asyncio.gather(*first, *second)

    replies = asyncio.run(scenario())
    assert all(r.status_code == 200 for r in replies)
    tab2 = [i for i, at in enumerate(store.order) if at >= 200]
    # The first read ran at once; then the tabs alternate: tab2's by the 6th read.
    assert tab2 == [2, 4, 6], store.order

    store2 = OrderedStore()
    app2 = create_app(Settings(api_read_workers=1, api_read_queue=32), store2)

    async def many_sessions():
        hostile = [
            asyncio.create_task(_session_get(app2, "10.0.0.1", store2.path(100 + i), f"s{i}"))
            for i in range(12)
        ]
        await asyncio.sleep(0.3)
        honest = [
            asyncio.create_task(_session_get(app2, "10.0.0.2", store2.path(200 + i), ""))
            for i in range(3)
        ]
        await asyncio.sleep(0.3)
        store2.release.set()
        return await asyncio.gather(*hostile, *honest)

    assert all(r.status_code == 200 for r in asyncio.run(many_sessions()))
    honest = [i for i, at in enumerate(store2.order) if at >= 200]
    assert honest == [2, 4, 6], store2.order


async def _session_get(app, address: str, path: str, session: str) -> httpx.Response:
    async with client_at(app, address) as client:
        return await client.get(path, headers={"X-Mapservice-Session": session}, timeout=60)


# The probes are timed and the turns ordered by the wall clock: run alone, as the other
# heavy requests' (tests/api/test_heavy_requests.py); beside the alone tests, at the lowest
# priority, the honest read once came two turns late.
@pytest.mark.integration
@pytest.mark.alone
def test_a_hostile_caller_with_many_sessions_gets_one_share_and_the_probes_stay_fast() -> None:
    """One address sends 100 reads at once, each naming a session of its own (as many
    connections, as many tabs): it runs MAPSERVICE_API_CALLER_CONCURRENCY and keeps
    MAPSERVICE_API_CALLER_QUEUE waiting, the rest are 429 at once (memory bounded); another
    address's read is served within its turn, and the probes answer within a second."""
    store = OrderedStore()
    settings = Settings(
        api_read_workers=2, api_read_queue=32, api_caller_concurrency=2, api_caller_queue=8
    )
    app = create_app(settings, store, {"clickhouse": lambda: True})

    async def scenario():
        hostile = [
            asyncio.create_task(_session_get(app, "10.6.6.6", store.path(1000 + i), f"tab{i}"))
            for i in range(100)
        ]
        # Until every read beyond the caller's share and queue is refused.
        for _ in range(300):
            if sum(t.done() for t in hostile) >= 100 - 2 - 8:
                break
            await asyncio.sleep(0.05)
        refused = [t.result() for t in hostile if t.done()]
        honest = asyncio.create_task(_get(app, "10.0.0.2", store.path(1)))
        await asyncio.sleep(0.2)
        probe_times = []
        for path in ("/healthz", "/readyz"):
            started = time.monotonic()
            reply = await asyncio.wait_for(_get(app, "10.9.9.9", path), timeout=5)
            probe_times.append(time.monotonic() - started)
            assert reply.status_code == 200
        store.release.set()
        return refused, await honest, await asyncio.gather(*hostile), probe_times

    refused, honest, hostile, probe_times = asyncio.run(scenario())
    assert len(refused) == 100 - 2 - 8
    assert {r.status_code for r in refused} == {429}
    assert all(r.headers["retry-after"].isdigit() for r in refused)
    assert honest.status_code == 200
    assert sum(r.status_code == 200 for r in hostile) == 2 + 8
    # The other address's read ran right after the first of the hostile caller's waiting
    # ones: one turn each, not after all eight.
    assert store.order.index(1) <= 2 + 1, store.order
    assert max(probe_times) < 1.0, probe_times


def test_a_read_whose_client_left_leaves_the_queue() -> None:
    """A page cancels a superseded read while it waits (the browser closes its connection):
    the read leaves the queue, its place free for the next, and never runs. On uvicorn: an
    in-process client never closes a connection."""
    store = OrderedStore()
    app = create_app(Settings(api_read_workers=1, api_read_queue=1), store)
    replies: dict[int, int] = {}

    def get(url: str, at: int) -> None:
        replies[at] = httpx.get(f"{url}{store.path(at)}", timeout=30).status_code

    def pool(active: int, waiting: int) -> None:
        # The read pool's own gauges: waits for states, not for times (a loaded machine).
        deadline = time.monotonic() + 30
        while (
            REGISTRY.get_sample_value("mapservice_api_pool_active", {"pool": "read"}),
            REGISTRY.get_sample_value("mapservice_api_pool_waiting", {"pool": "read"}),
        ) != (
            active,
            waiting,
        ):
            assert time.monotonic() < deadline, f"the read pool never had {active} + {waiting}"
            time.sleep(0.02)

    with served(app) as (port, _):
        url = f"http://127.0.0.1:{port}"
        stuck = threading.Thread(target=get, args=(url, 1))
        stuck.start()
        pool(active=1, waiting=0)
        with socket.create_connection(("127.0.0.1", port)) as left:
            left.sendall(f"GET {store.path(2)} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
            pool(active=1, waiting=1)
        pool(active=1, waiting=0)  # the read whose client left is out of the queue
        queued = threading.Thread(target=get, args=(url, 3))
        queued.start()
        pool(active=1, waiting=1)
        store.release.set()
        stuck.join(30)
        queued.join(30)
    assert replies == {1: 200, 3: 200}  # 3 not 503: the place 2 held was free again
    assert store.order == [1, 3]


def _sql_app(release: threading.Event):
    """An analysts' engine stand-in whose every query waits for `release`."""

    async def app(scope, receive, send):
        await asyncio.get_running_loop().run_in_executor(None, release.wait, 30)
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"1\n"})

    return app


def test_analysts_queries_are_rate_limited_and_left_to_their_own_gate() -> None:
    """/clickhouse no longer bypasses the rate limit; it takes no read pool slot and no
    per-caller slot (the analysts' query gate bounds it, mapservice/sql/query_gate.py), so
    analysts waiting on their engine never make a caller's reads 429 or 503."""
    release = threading.Event()
    release.set()
    limited = TestClient(
        create_app(Settings(api_rate_limit="2/minute"), MemoryStore(), sql_app=_sql_app(release))
    )
    assert [limited.get("/clickhouse/?query=SELECT+1").status_code for _ in range(3)] == [
        200,
        200,
        429,
    ]

    release.clear()
    app = create_app(
        Settings(api_read_workers=1, api_read_queue=0, api_caller_concurrency=1),
        MemoryStore(),
        sql_app=_sql_app(release),
    )

    async def scenario():
        waiting = [
            asyncio.create_task(_get(app, "10.0.0.1", "/clickhouse/?query=SELECT+1"))
            for _ in range(3)
        ]
        await asyncio.sleep(0.3)
        read = await _get(app, "10.0.0.1", "/api/v1/robots")
        release.set()
        return [await w for w in waiting], read

    analysts, read = asyncio.run(scenario())
    assert read.status_code == 200, read.text
    assert [a.status_code for a in analysts] == [200, 200, 200]


def test_the_live_stream_is_rate_limited_and_capped_per_caller() -> None:
    """Opening /api/v1/live counts against MAPSERVICE_API_RATE_LIMIT (it used to bypass it),
    and one caller holds at most MAPSERVICE_API_LIVE_CLIENTS_PER_CALLER connections: both
    refused with 429 and a JSON reason."""
    client = TestClient(
        create_app(Settings(api_rate_limit="2/minute"), MemoryStore(), live_hub=LiveHub())
    )
    for _ in range(2):
        with client.websocket_connect(LIVE_URL) as ws:
            ws.close()
    with pytest.raises(WebSocketDenialResponse) as over:
        with client.websocket_connect(LIVE_URL):
            pass
    assert (
        over.value.status_code == 429 and "MAPSERVICE_API_RATE_LIMIT" in over.value.json()["detail"]
    )

    capped = TestClient(
        create_app(Settings(api_live_clients_per_caller=1), MemoryStore(), live_hub=LiveHub())
    )
    with capped.websocket_connect(LIVE_URL):
        with pytest.raises(WebSocketDenialResponse) as second:
            with capped.websocket_connect(LIVE_URL):
                pass
    assert second.value.status_code == 429
    assert "MAPSERVICE_API_LIVE_CLIENTS_PER_CALLER" in second.value.json()["detail"]
    with capped.websocket_connect(LIVE_URL) as again:  # the first one closed: a place again
        again.close()


def test_probes_and_pages_belong_to_no_pool() -> None:
    """With the reads' pool taken and its queue full, the probes and the UI's pages still
    answer: only /api/..., exports and /clickhouse are pooled."""
    store = StuckStore()
    app = create_app(Settings(api_read_workers=1, api_read_queue=0), store)

    async def scenario():
        stuck = asyncio.create_task(_get(app, "10.0.0.1", "/api/v1/robots"))
        await asyncio.sleep(0.2)
        replies = [
            await _get(app, "10.0.0.2", p) for p in ("/api/v1/robots", "/healthz", "/readyz")
        ]
        store.release.set()
        await stuck
        return replies

    pooled, health, ready = asyncio.run(scenario())
    assert pooled.status_code == 503
    assert health.status_code == 200 and ready.status_code == 200


def test_analysts_are_rate_limited_per_credential_not_per_address() -> None:
    """/clickhouse's callers authenticate with the analyst credential (HTTP Basic or
    X-ClickHouse-User/-Key): its rate limit counts per credential, so an analyst on several
    machines has one budget; a wrong password counts against the client's address."""
    from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app

    sql_app = clickhouse_http_app(object(), [SqlUser("analyst", "s3cret", read_only=True)])  # type: ignore[arg-type]
    app = create_app(Settings(api_rate_limit="2/minute"), MemoryStore(), sql_app=sql_app)

    async def get(address: str, **headers) -> int:
        async with client_at(app, address) as client:
            return (await client.get("/clickhouse/ping", headers=headers, timeout=30)).status_code

    async def scenario():
        basic = {"Authorization": "Basic " + base64.b64encode(b"analyst:s3cret").decode()}
        keyed = {"X-ClickHouse-User": "analyst", "X-ClickHouse-Key": "s3cret"}
        wrong = {"X-ClickHouse-User": "analyst", "X-ClickHouse-Key": "guess"}
        return [
            await get("10.0.0.1", **basic),
            await get("10.0.0.2", **keyed),
            await get("10.0.0.3", **basic),
            await get("10.0.0.3", **wrong),
            await get("10.0.0.3", **wrong),
        ]

    assert asyncio.run(scenario()) == [200, 200, 429, 200, 200]
