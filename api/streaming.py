"""Exports streamed with backpressure: a producer writes in a thread of the exports' own
pool, the response sends, and between them at most a few chunks wait.

A client that stops reading fills its socket, then the transport's buffer (uvicorn pauses
at 64 KB), then this pipe's `max_chunks` chunks; the producer's next write then blocks
until the client reads again or the export is aborted (api/admission.py's deadline, or
the client leaving), when it raises `ExportAborted` and the producer stops. So a client
that never reads holds at most about `max_chunks` x `chunk_bytes` plus what the producer
is working on (one slice of a table, one MCAP chunk), never the whole export.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor

CHUNK_BYTES = 256 * 1024
MAX_CHUNKS = 8
_DONE = object()


class ExportAborted(Exception):
    """The response side is gone (deadline, client left): the producer must stop."""


class BoundedPipe:
    """A write-only file for the producer thread; `chunks()` for the response."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        chunk_bytes: int = CHUNK_BYTES,
        max_chunks: int = MAX_CHUNKS,
    ) -> None:
        self.loop, self.chunk_bytes = loop, chunk_bytes
        self._slots = threading.Semaphore(max_chunks)
        self._queue: asyncio.Queue = asyncio.Queue()
        self._buffer = bytearray()
        self._written = 0
        self._aborted = threading.Event()

    # --- the producer's side (a thread) -------------------------------------------------

    def write(self, data: bytes) -> int:
        self._buffer += data
        # The first bytes go at once: the response starts (status, headers) as soon as the
        # producer got past what may still fail with a 4xx.
        if len(self._buffer) >= self.chunk_bytes or not self._written:
            self._put(bytes(self._buffer))
            self._buffer.clear()
        self._written += len(data)
        return len(data)

    def tell(self) -> int:  # the MCAP writer records offsets
        return self._written

    def flush(self) -> None:
        pass

    def _put(self, item) -> None:
        while not self._slots.acquire(timeout=0.5):
            if self._aborted.is_set():
                raise ExportAborted("the export was aborted (deadline, or the client left)")
        if self._aborted.is_set():
            raise ExportAborted("the export was aborted (deadline, or the client left)")
        self.loop.call_soon_threadsafe(self._queue.put_nowait, item)

    def finish(self, error: BaseException | None = None) -> None:
        """The producer's last call: what is buffered, then the end (or the error)."""
        try:
            if error is None and self._buffer:
                self._put(bytes(self._buffer))
                self._buffer.clear()
        except ExportAborted:
            return
        self.loop.call_soon_threadsafe(
            self._queue.put_nowait, error if error is not None else _DONE
        )

    # --- the response's side (the event loop) -------------------------------------------

    async def first(self) -> bytes | None:
        """The first chunk (None: the export is empty); raises what the producer raised
        before writing anything, so a route can still answer it with a 4xx."""
        return await self._next()

    async def _next(self) -> bytes | None:
        item = await self._queue.get()
        if item is _DONE:
            return None
        if isinstance(item, BaseException):
            raise item
        self._slots.release()
        return item

    async def chunks(self, first: bytes | None) -> AsyncIterator[bytes]:
        try:
            if first is None:
                return
            yield first
            while (item := await self._next()) is not None:
                yield item
        finally:
            self._aborted.set()  # done, cancelled or failed: a blocked producer stops

    def abort(self) -> None:
        self._aborted.set()


async def produce(
    executor: Executor, producer: Callable[[BoundedPipe], object], **pipe_options
) -> tuple[BoundedPipe, bytes | None]:
    """Starts `producer(pipe)` in `executor`; returns the pipe and its first chunk (what
    the producer raised before its first byte is raised here)."""
    loop = asyncio.get_running_loop()
    pipe = BoundedPipe(loop, **pipe_options)

    def run() -> None:
        try:
            producer(pipe)
        except ExportAborted:
            pipe.finish(ExportAborted("aborted"))
        except BaseException as exc:  # noqa: BLE001 - handed to the response side
            pipe.finish(exc)
        else:
            pipe.finish()

    loop.run_in_executor(executor, run)
    try:
        return pipe, await pipe.first()
    except BaseException:
        pipe.abort()
        raise
