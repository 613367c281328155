"""A request body's Content-Encoding undone within a cap on what it decodes to.

Each decoder is asked, step by step, for a bounded piece of output, and decoding stops as
soon as the pieces pass the cap: 300 KB of gzip that would become 300 MB costs the cap
plus one step in memory, and its refusal comes after the cap's worth of work, not the
bomb's. The decoders are the libraries' incremental ones (zlib's decompressobj with
`max_length`, lz4's frame decompressor with `max_length`, zstandard's decompressobj); none
of them is ever handed the whole body to decode at once.

This is CPU work: callers run it off the event loop (mapservice/sql/request_body.py).
"""

from __future__ import annotations

import io
import zlib
from collections.abc import Iterator

from mapservice.sql.engine import NOT_IMPLEMENTED, SqlError

TOO_LARGE = 131  # ClickHouse's TOO_LARGE_STRING_SIZE: a 400 over HTTP
CANNOT_DECOMPRESS = 271
ENCODINGS = ("gzip", "deflate", "lz4", "zstd")
# The most one decoding step produces (and so the most decoding overshoots the cap by).
OUTPUT_STEP = 256 * 1024
# zstd: the largest window a body may ask for. RFC 8878 asks decoders to support 8 MiB;
# without a bound a 20-byte frame header makes the decoder reserve up to 2 GiB.
ZSTD_MAX_WINDOW = 8 * 1024 * 1024
# zstd's decompressobj has no max_length. A zstd block decodes to at most 128 KiB and
# takes at least 4 bytes (an RLE block), so feeding it at most room/32,768 bytes at a
# time keeps each step's output within the room left (plus the one block in progress).
_ZSTD_MAX_RATIO = 128 * 1024 // 4


class BodyTooLarge(SqlError):
    def __init__(self, limit: int, advice: str, decoded: bool):
        what = "decodes to more than" if decoded else "is larger than"
        super().__init__(f"The request body {what} {limit} bytes, the limit: {advice}", TOO_LARGE)
        self.limit = limit


def content_encoding(header: str) -> str:
    """The one encoding a Content-Encoding header names ("" for none), or a clear 400."""
    encoding = header.strip().lower()
    if "," in encoding:
        raise SqlError(
            f"Content-Encoding {header!r} stacks encodings; send the body encoded once, "
            f"with one of {', '.join(ENCODINGS)}",
            NOT_IMPLEMENTED,
        )
    if encoding in ("", "identity") or encoding in ENCODINGS:
        return "" if encoding == "identity" else encoding
    raise SqlError(
        f"Unknown Content-Encoding {header!r}; send {', '.join(ENCODINGS)} or none",
        NOT_IMPLEMENTED,
    )


def decode(body: bytes, encoding: str, limit: int, advice: str) -> bytes:
    """`body` with `encoding` (from `content_encoding`) undone; BodyTooLarge past `limit`
    bytes of output, a 400 naming the encoding if it does not decode."""
    if not encoding:
        if len(body) > limit:
            raise BodyTooLarge(limit, advice, decoded=False)
        return body
    # BytesIO: getvalue() hands over its buffer, so a body near the cap is held once.
    out = io.BytesIO()
    try:
        for piece in _PIECES[encoding](body, limit):
            if out.write(piece) and out.tell() > limit:
                raise BodyTooLarge(limit, advice, decoded=True)
    except SqlError:
        raise
    except Exception as exc:  # zlib, lz4 and zstandard each raise their own kind
        raise SqlError(
            f"Cannot decode the {encoding} request body: {exc}; send it {encoding}-encoded "
            "whole, or without Content-Encoding",
            CANNOT_DECOMPRESS,
        ) from exc
    return out.getvalue()


def _zlib_pieces(body: bytes, wbits: int, members: bool) -> Iterator[bytes]:
    data = body
    while True:
        stream = zlib.decompressobj(wbits)
        while True:
            piece = stream.decompress(data, OUTPUT_STEP)
            if piece:
                yield piece
            data = stream.unconsumed_tail
            if stream.eof or not (piece or data):
                break
        if not stream.eof:
            raise ValueError("the compressed stream ends before its end marker (truncated?)")
        # gzip: another member may follow (as gzip.decompress reads them); zeros are padding.
        data = stream.unused_data
        if not members or not data.strip(b"\0"):
            return


def _gzip_pieces(body: bytes, _limit: int) -> Iterator[bytes]:
    return _zlib_pieces(body, 16 + zlib.MAX_WBITS, members=True)


def _deflate_pieces(body: bytes, _limit: int) -> Iterator[bytes]:
    # HTTP's "deflate" is the zlib format (RFC 9110), what zlib.decompress reads.
    return _zlib_pieces(body, zlib.MAX_WBITS, members=False)


def _lz4_pieces(body: bytes, _limit: int) -> Iterator[bytes]:
    import lz4.frame

    data = body
    while data:
        frame = lz4.frame.LZ4FrameDecompressor()
        yield frame.decompress(data, max_length=OUTPUT_STEP)
        while not frame.eof and not frame.needs_input:
            yield frame.decompress(b"", max_length=OUTPUT_STEP)
        if not frame.eof:
            raise ValueError("the lz4 frame ends before its end mark (truncated?)")
        data = frame.unused_data


def _zstd_pieces(body: bytes, limit: int) -> Iterator[bytes]:
    import zstandard

    decompressor = zstandard.ZstdDecompressor(max_window_size=ZSTD_MAX_WINDOW)
    view, at, produced = memoryview(body), 0, 0
    while at < len(body):
        frame = decompressor.decompressobj()
        while not frame.eof and at < len(body):
            step = max(4, (limit + 1 - produced) // _ZSTD_MAX_RATIO)
            piece = frame.decompress(view[at : at + step])
            at += step
            produced += len(piece)
            yield piece
        if not frame.eof:
            raise ValueError("the zstd frame ends before its last block (truncated?)")
        # The next frame starts where this one ended, inside the last piece fed.
        at = min(at, len(body)) - len(frame.unused_data)


_PIECES = {
    "gzip": _gzip_pieces,
    "deflate": _deflate_pieces,
    "lz4": _lz4_pieces,
    "zstd": _zstd_pieces,
}
