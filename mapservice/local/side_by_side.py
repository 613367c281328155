"""Start-up steps that do not wait on each other, run at once: a component's start is mostly
its interpreter importing and its dependencies answering, so components started side by
side are up in about the time of the slowest, not of all of them in a row."""

from __future__ import annotations

import threading
from collections.abc import Callable


class SideBySide:
    """Runs steps side by side and remembers the threads it started, so that whoever stops
    what they started can wait for them (`join`): a step still running then ends as soon as
    the process it waits for is stopped."""

    def __init__(self, poll_s: float = 0.1) -> None:
        self.poll_s = poll_s
        self._threads: list[threading.Thread] = []

    def run(self, here: Callable[[], object], *elsewhere: Callable[[], object]) -> None:
        """`here` in this thread (a step that cleans up after itself when interrupted, as
        Ctrl-C reaches only this thread), each of `elsewhere` in a thread of its own; returns
        when all are done. A step's failure is raised as soon as it fails, the others left
        running (stop what they started, then `join`)."""
        errors: list[BaseException] = []
        threads = []
        for step in elsewhere:
            thread = threading.Thread(target=self._step, args=(step, errors), daemon=True)
            self._threads.append(thread)
            threads.append(thread)
            thread.start()
        here()
        while True:
            if errors:
                raise errors[0]
            running = [thread for thread in threads if thread.is_alive()]
            if not running:
                break
            running[0].join(self.poll_s)
        if errors:
            raise errors[0]

    @staticmethod
    def _step(step: Callable[[], object], errors: list[BaseException]) -> None:
        try:
            step()
        except BaseException as exc:  # raised in the thread that waits for the steps
            errors.append(exc)

    def join(self, timeout_s: float = 60.0) -> None:
        """Waits (at most `timeout_s` each) for the steps still running, and forgets them."""
        for thread in self._threads:
            thread.join(timeout_s)
        self._threads.clear()
