"""Chunk pixels kept in memory by content hash, one cache per API app (api/context.py):
contents are immutable per hash, so a hit never goes stale."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from cachetools import LRUCache

from mapservice.core.ports import TimeTravelReader

# Bytes of zlib pixels kept in memory per app (a 100x100 chunk is ~0.1-2 KiB compressed).
CACHE_BYTES = 64 * 1024 * 1024

Content = tuple[int, int, bytes]


class ContentCache:
    """Content is immutable per hash, so a hit never goes stale; bounded by bytes held."""

    def __init__(self, max_bytes: int = CACHE_BYTES) -> None:
        self._lru: LRUCache[bytes, Content] = LRUCache(
            max_bytes, getsizeof=lambda c: len(c[2]) + 64
        )
        self._lock = threading.Lock()  # the endpoints run in the threadpool

    def get_many(self, store: TimeTravelReader, hashes: Sequence[bytes]) -> dict[bytes, Content]:
        found: dict[bytes, Content] = {}
        with self._lock:
            for h in hashes:
                c = self._lru.get(h)
                if c is not None:
                    found[h] = c
        todo = [h for h in dict.fromkeys(hashes) if h not in found]
        if todo:
            fresh = store.chunk_contents(todo) if len(todo) > 1 else _one(store, todo[0])
            with self._lock:
                for h, c in fresh.items():
                    if len(c[2]) + 64 <= self._lru.maxsize:
                        self._lru[h] = c
            found.update(fresh)
        return found


def _one(store: TimeTravelReader, h: bytes) -> dict[bytes, Content]:
    c = store.chunk_content(h)
    return {} if c is None else {h: c}
