"""The analysts' own bounded pool: a few threads of their own, a short queue, and "too many
queries" (HTTP 503 with Retry-After) for everyone beyond it.

Analysts' statements never run on anyio's worker threads, which the API's sync routes and
probes share: 60 `SELECT sleep(3)` used to hold all 40 of them. Here at most `concurrent`
statements run (each under its own `max_memory_usage`, so their memory in total is
bounded too), at most `queued` more wait up to `queue_timeout_s` for a thread, and the
rest are refused at once, before any work is done for them.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

from mapservice.sql.engine import TOO_MANY_SIMULTANEOUS_QUERIES, SqlError

T = TypeVar("T")


class TooManyQueries(SqlError):
    def __init__(self, message: str, retry_after_s: int):
        super().__init__(message, TOO_MANY_SIMULTANEOUS_QUERIES)
        self.retry_after_s = retry_after_s


class QueryGate:
    """Admits a call to a thread of its own pool, or refuses it with TooManyQueries."""

    def __init__(
        self,
        concurrent: int,
        queued: int,
        queue_timeout_s: float,
        name: str = "analyst-sql",
        who: str = "analysts",
    ):
        if concurrent < 1 or queued < 0:
            raise ValueError("a query gate needs at least one thread and a queue of 0 or more")
        self.concurrent, self.queued, self.queue_timeout_s = concurrent, queued, queue_timeout_s
        self.who = who  # named in a refusal
        self._executor = ThreadPoolExecutor(concurrent, thread_name_prefix=name)
        self._admitted = 0  # running or waiting; touched only on the event loop's thread
        self._slots: asyncio.Semaphore | None = None

    @property
    def admitted(self) -> int:
        return self._admitted

    def _refuse(self, why: str) -> TooManyQueries:
        retry = max(1, math.ceil(self.queue_timeout_s))
        return TooManyQueries(
            f"Too many simultaneous queries for {self.who} ({why}: {self.concurrent} run at a "
            f"time, {self.queued} wait). Too many queries: retry after {retry} s. "
            "(TOO_MANY_SIMULTANEOUS_QUERIES)",
            retry,
        )

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        if self._slots is None:
            self._slots = asyncio.Semaphore(self.concurrent)
        if self._admitted >= self.concurrent + self.queued:
            raise self._refuse("the queue is full")
        self._admitted += 1
        slots = self._slots
        try:
            # asyncio.timeout, not wait_for: on 3.11 wait_for can lose a slot acquired just
            # as it times out.
            async with asyncio.timeout(self.queue_timeout_s):
                await slots.acquire()
        except TimeoutError:
            self._admitted -= 1
            raise self._refuse(f"waited {self.queue_timeout_s:g} s for a slot") from None
        except BaseException:
            self._admitted -= 1
            raise
        future = asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

        def release(done: asyncio.Future[T]) -> None:
            # When the statement ends, not when its caller gives up: an abandoned statement
            # keeps its engine thread until it finishes (or hits max_execution_time).
            self._admitted -= 1
            slots.release()
            if not done.cancelled():
                done.exception()  # an abandoned statement's error is not "never retrieved"

        future.add_done_callback(release)
        return await asyncio.shield(future)

    def close(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
