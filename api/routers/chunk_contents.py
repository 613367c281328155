"""Chunk pixels by content hash: content-addressed, so cacheable forever.

One hash at a time (`GET /{hash}`), or many in one request (`POST /batch`), which the
replay UI uses on a seek: hundreds of pictures in a few responses instead of hundreds of
requests, each needing its own database read.
"""

from __future__ import annotations

import re
import threading
import zlib
from collections.abc import Sequence

import msgspec
from cachetools import LRUCache
from fastapi import APIRouter, Body, Depends, HTTPException, Query, Request, Response

from mapservice.core.ports import TimeTravelReader
from mapservice.core.render import chunk_pixels, png

from ..access import READ
from ..deps import get_store

router = APIRouter(
    prefix="/api/v1/chunk-contents", tags=["chunk-contents"], dependencies=[Depends(READ)]
)
_HEX32 = re.compile(r"^[0-9a-f]{32}$")
IMMUTABLE = "public, max-age=31536000, immutable"
BATCH_MAX = 2000
MSGPACK = "application/vnd.msgpack"
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


_cache_lock = threading.Lock()


def get_cache(request: Request) -> ContentCache:
    """One cache per app (so per store: tests build many apps over different stores)."""
    state = request.app.state
    with _cache_lock:
        cache = getattr(state, "chunk_content_cache", None)
        if cache is None:
            cache = state.chunk_content_cache = ContentCache()
    return cache


class BatchResponse(msgspec.Struct):
    contents: list[tuple[str, int, int, bytes]]
    missing: list[str]


_encoder = msgspec.msgpack.Encoder()


@router.post(
    "/batch",
    operation_id="getChunkContentsBatch",
    summary=f"Many chunk contents in one MessagePack response (at most {BATCH_MAX} hashes)",
    description=(
        f'Body: `{{"hashes": [...]}}`, 1 to {BATCH_MAX} content hashes (32 lowercase hex '
        "characters each; duplicates are answered once). Answer (`application/vnd.msgpack`): "
        'a map `{"contents": [[hash, width, height, zlib pixels (bin)], ...], '
        '"missing": [hash, ...]}`; the pixels are as the robot sent them (PGM grey levels: '
        "0 occupied, 205 unknown, 254/255 free). Contents are immutable per hash."
    ),
    responses={
        200: {"content": {MSGPACK: {}}},
        400: {"description": "malformed or too many hashes"},
    },
)
def get_chunk_contents_batch(
    hashes: list[str] = Body(..., embed=True),
    store: TimeTravelReader = Depends(get_store),
    cache: ContentCache = Depends(get_cache),
) -> Response:
    if not hashes:
        raise HTTPException(400, f"hashes is empty; send 1 to {BATCH_MAX} content hashes")
    if len(hashes) > BATCH_MAX:
        raise HTTPException(
            400, f"{len(hashes)} hashes in one batch; send at most {BATCH_MAX} per request"
        )
    bad = [h for h in hashes if not _HEX32.match(h)]
    if bad:
        raise HTTPException(
            400, f"hashes must be 32 lowercase hex characters; bad: {[b[:40] for b in bad[:5]]!r}"
        )
    wanted = list(dict.fromkeys(hashes))
    found = cache.get_many(store, [bytes.fromhex(h) for h in wanted])
    contents, missing = [], []
    for h in wanted:
        c = found.get(bytes.fromhex(h))
        if c is None:
            missing.append(h)
        else:
            contents.append((h, c[0], c[1], c[2]))
    body = _encoder.encode(BatchResponse(contents=contents, missing=missing))
    return Response(body, media_type=MSGPACK)


@router.get(
    "/{content_hash}",
    operation_id="getChunkContent",
    responses={200: {"content": {"application/octet-stream": {}, "image/png": {}}}},
)
def get_chunk_content(
    content_hash: str,
    encoding: str = Query(
        "zlib",
        pattern="^(zlib|raw|png)$",
        description="zlib: as the robot sent it; raw: width x height bytes; png",
    ),
    store: TimeTravelReader = Depends(get_store),
    cache: ContentCache = Depends(get_cache),
) -> Response:
    if not _HEX32.match(content_hash):
        raise HTTPException(400, "content_hash must be 32 lowercase hex characters")
    key = bytes.fromhex(content_hash)
    found = cache.get_many(store, [key]).get(key)
    if found is None:
        raise HTTPException(404, f"no chunk content with hash {content_hash}")
    width, height, data = found
    if encoding == "png":
        body, media = png(chunk_pixels(width, height, data)), "image/png"
    else:
        body = data if encoding == "zlib" else zlib.decompress(data)
        media = "application/octet-stream"
    return Response(
        body,
        media_type=media,
        headers={
            "Cache-Control": IMMUTABLE,
            "ETag": f'"{content_hash}"',
            "X-Chunk-Width": str(width),
            "X-Chunk-Height": str(height),
        },
    )
