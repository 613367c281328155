"""What the 2019 chunk service tests share: a store holding a meta and fourteen chunk writes
(two of them at one instant in one cell), an app over it with a writer token, and helpers
to list and compare chunks."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from tests.fixtures.legacy import SpyStore

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
CLOCK_MS = NOW + 60_000
TOKEN = "test-admin-token"
ADMIN = {"Authorization": f"Bearer {TOKEN}"}
WRITER_TOKEN = "test-writer-token"  # a 2019 robot's: the header is all it adds
WRITER = {"Authorization": f"Bearer {WRITER_TOKEN}"}
JSON = {"Content-Type": "application/json"}
BASE = "/api/chunk-service"


def pixels(i: int) -> bytes:
    return bytes([i]) * 10_000


# (robot, offset ms, row, column) per write; writes 12 and 13 overwrite cell (0, 0) at one
# instant, and r2 > r1 wins it.
WRITES = [(f"r{i % 3}", i * 1000, i % 4, i % 5) for i in range(12)] + [
    ("r1", 12_000, 0, 0),
    ("r2", 12_000, 0, 0),
]


@pytest.fixture
def store(ev) -> SpyStore:
    s = SpyStore()
    s.append([ev.meta(NOW - 10_000, chunk_rows=4, chunk_cols=5)])
    s.append(
        [
            ev.chunk(robot, NOW + dt, row, col, pixels(i))
            for i, (robot, dt, row, col) in enumerate(WRITES)
        ]
    )
    return s


@pytest.fixture
def publisher() -> MemoryPublisher:
    return MemoryPublisher()


@pytest.fixture
def settings() -> Settings:
    return Settings(admin_token=TOKEN, api_writer_tokens=WRITER_TOKEN)


@pytest.fixture
def client(store, publisher, settings) -> TestClient:
    app = create_app(settings, store, {}, ManualClock(CLOCK_MS), publisher=publisher)
    return TestClient(app, raise_server_exceptions=False, headers=WRITER)


def anonymous(client: TestClient) -> TestClient:
    """The same app, asked without a credential."""
    return TestClient(client.app, raise_server_exceptions=False)


def get(client, **params):
    r = client.get(f"{BASE}/chunks", params=params)
    assert r.status_code == 200, r.text
    return r.json()


def keys(body) -> list[tuple]:
    """(robot, offset ms, row, column) of each returned chunk, in order."""
    return [(c["robotId"], _ms(c["timestamp"]) - NOW, c["row"], c["column"]) for c in body]


def _ms(ts: str) -> int:
    from mapservice.core.wire2019 import parse_timestamp

    return parse_timestamp(ts)


def newest_first(writes):
    return sorted(writes, key=lambda w: (-w[1], w[2], w[3], w[0]))
