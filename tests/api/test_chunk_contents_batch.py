"""POST /api/v1/chunk-contents/batch (MessagePack) and the content cache behind both reads."""

from __future__ import annotations

import zlib

import msgspec
import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.api.content_cache import ContentCache
from mapservice.api.routers.chunk_contents import BATCH_MAX, MSGPACK
from mapservice.core.wire2019 import content_hash
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000
URL = "/api/v1/chunk-contents/batch"
A = bytes(i % 256 for i in range(100 * 100))
B = bytes([205]) * 10_000
HA, HB = content_hash(A).hex(), content_hash(B).hex()
UNKNOWN = "0" * 32


class CountingStore(MemoryStore):
    """A MemoryStore that counts content reads (single and batch)."""

    def __init__(self) -> None:
        super().__init__()
        self.reads: list[tuple[str, int]] = []

    def chunk_content(self, h):
        self.reads.append(("one", 1))
        return super().chunk_content(h)

    def chunk_contents(self, hashes):
        self.reads.append(("many", len(hashes)))
        return super().chunk_contents(hashes)


@pytest.fixture
def store(ev) -> CountingStore:
    s = CountingStore()
    s.append([ev.chunk("r1", NOW, 0, 0, A), ev.chunk("r2", NOW + 1, 0, 1, B)])
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(NOW + 60_000)), raise_server_exceptions=False
    )


def _decode(r) -> dict:
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == MSGPACK
    return msgspec.msgpack.decode(r.content)


def test_batch_returns_known_contents_and_lists_missing(client, store) -> None:
    """Known hashes come back as [hash, width, height, zlib bytes] in request order; unknown are missing."""
    body = _decode(client.post(URL, json={"hashes": [HB, UNKNOWN, HA, HB]}))
    assert [c[0] for c in body["contents"]] == [HB, HA]
    for h, w, ht, data in body["contents"]:
        assert (w, ht) == (100, 100)
        assert data == store.chunk_content(bytes.fromhex(h))[2]
    assert zlib.decompress(body["contents"][1][3]) == A
    assert body["missing"] == [UNKNOWN]


def test_batch_reads_the_store_once(client, store) -> None:
    """One batch is one store.chunk_contents call, and a repeat is served from the cache."""
    _decode(client.post(URL, json={"hashes": [HA, HB, UNKNOWN]}))
    assert store.reads == [("many", 3)]
    _decode(client.post(URL, json={"hashes": [HA, HB]}))
    assert store.reads == [("many", 3)]


def test_single_read_uses_the_cache(client, store) -> None:
    """A hash fetched by batch is then served by GET /{hash} without another store read."""
    _decode(client.post(URL, json={"hashes": [HA, HB]}))
    r = client.get(f"/api/v1/chunk-contents/{HA}", params={"encoding": "raw"})
    assert r.status_code == 200 and r.content == A
    assert store.reads == [("many", 2)]


def test_batch_at_the_limit_is_accepted(client) -> None:
    """Exactly BATCH_MAX hashes (2,000) is allowed."""
    assert BATCH_MAX == 2000
    hashes = [HA] + [f"{i:032x}" for i in range(1, BATCH_MAX)]
    body = _decode(client.post(URL, json={"hashes": hashes}))
    assert [c[0] for c in body["contents"]] == [HA] and len(body["missing"]) == BATCH_MAX - 1


@pytest.mark.parametrize(
    "hashes, words",
    [
        ([f"{i:032x}" for i in range(BATCH_MAX + 1)], "at most 2000"),
        ([], "empty"),
        ([HA, HA.upper()], "32 lowercase hex"),
        (["abc"], "32 lowercase hex"),
    ],
)
def test_bad_batch_is_400_with_a_message(client, hashes, words) -> None:
    """Too many, none, or malformed hashes are a 400 that says what to fix."""
    r = client.post(URL, json={"hashes": hashes})
    assert r.status_code == 400 and words in r.json()["detail"]


def test_batch_without_hashes_field_is_422(client) -> None:
    """A body without `hashes` is rejected by validation."""
    assert client.post(URL, json={"hash": [HA]}).status_code == 422


def test_cache_is_bounded_by_bytes(store) -> None:
    """The cache evicts least recently used contents past its byte bound."""
    a, b = bytes.fromhex(HA), bytes.fromhex(HB)
    size_a = len(store.chunk_content(a)[2])
    cache = ContentCache(max_bytes=size_a + 64)
    store.reads.clear()
    cache.get_many(store, [a])
    cache.get_many(store, [b])  # evicts a
    cache.get_many(store, [a])
    assert [kind for kind, _ in store.reads] == ["one", "one", "one"]
