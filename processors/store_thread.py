"""The one thread the processors talk to the store on.

Every store call of the processors (the history inserts, the live views' loads and
conflict writes, the snapshot timer, the migration in one process) goes through one
`StoreThread`: one thread keeps them in the order they were handed over (a view rebuilt
at an assignment sees exactly what was stored before it), keeps the blocking store off the
event loop, and keeps embedded chDB to one caller. The composition (composition.py)
makes it once and hands it to every part that needs it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")


class StoreThread:
    def __init__(self, name: str = "history") -> None:
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on the store thread, after everything handed over before it."""
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)

    def close(self) -> None:
        """Waits for what was handed over, then ends the thread."""
        self.executor.shutdown(wait=True)
