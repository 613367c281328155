"""Chunk pixels by content hash: content-addressed, so cacheable forever.

One hash at a time (`GET /{hash}`), or many in one request (`POST /batch`), which the
replay UI uses on a seek: hundreds of pictures in a few responses instead of hundreds of
requests, each needing its own database read.
"""

from __future__ import annotations

import re
import zlib

import msgspec
from fastapi import APIRouter, Body, Depends, HTTPException, Query, Response

from mapservice.core.render import chunk_pixels, png

from ..access import READ
from ..deps import ContentCacheDep, HistoryDep

router = APIRouter(
    prefix="/api/v1/chunk-contents", tags=["chunk-contents"], dependencies=[Depends(READ)]
)
_HEX32 = re.compile(r"^[0-9a-f]{32}$")
IMMUTABLE = "public, max-age=31536000, immutable"
BATCH_MAX = 2000
MSGPACK = "application/vnd.msgpack"


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
    *,
    store: HistoryDep,
    cache: ContentCacheDep,
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
    *,
    store: HistoryDep,
    cache: ContentCacheDep,
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
