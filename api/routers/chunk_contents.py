"""Chunk pixels by content hash: content-addressed, so cacheable forever."""

from __future__ import annotations

import re
import zlib

from fastapi import APIRouter, Depends, HTTPException, Query, Response

from mapservice.ports import HistoryStore
from mapservice.render import chunk_pixels, png

from ..deps import get_store

router = APIRouter(prefix="/api/v1/chunk-contents", tags=["chunk-contents"])
_HEX32 = re.compile(r"^[0-9a-f]{32}$")
IMMUTABLE = "public, max-age=31536000, immutable"


@router.get("/{content_hash}", operation_id="getChunkContent",
            responses={200: {"content": {"application/octet-stream": {}, "image/png": {}}}})
def get_chunk_content(
    content_hash: str,
    encoding: str = Query("zlib", pattern="^(zlib|raw|png)$",
                          description="zlib: as the robot sent it; raw: width x height bytes; png"),
    store: HistoryStore = Depends(get_store),
) -> Response:
    if not _HEX32.match(content_hash):
        raise HTTPException(400, "content_hash must be 32 lowercase hex characters")
    found = store.chunk_content(bytes.fromhex(content_hash))
    if found is None:
        raise HTTPException(404, f"no chunk content with hash {content_hash}")
    width, height, data = found
    if encoding == "png":
        body, media = png(chunk_pixels(width, height, data)), "image/png"
    else:
        body = data if encoding == "zlib" else zlib.decompress(data)
        media = "application/octet-stream"
    return Response(body, media_type=media, headers={
        "Cache-Control": IMMUTABLE, "ETag": f'"{content_hash}"',
        "X-Chunk-Width": str(width), "X-Chunk-Height": str(height)})
