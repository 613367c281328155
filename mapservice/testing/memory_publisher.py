"""An in-process log for tests and pure runs: records per topic, delivery on poll()."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable


class MemoryPublisher:
    def __init__(self, fail_with: Exception | None = None) -> None:
        self.records: dict[str, list[tuple[bytes, bytes]]] = defaultdict(list)
        self._pending: list[tuple[str, bytes, bytes, Callable[[Exception | None], None]]] = []
        self.fail_with = fail_with
        self.closed = False

    def publish(
        self, topic: str, key: bytes, value: bytes, on_done: Callable[[Exception | None], None]
    ) -> None:
        self._pending.append((topic, key, value, on_done))

    def poll(self, timeout: float = 0.0) -> None:
        pending, self._pending = self._pending, []
        for topic, key, value, on_done in pending:
            if self.fail_with is None:
                self.records[topic].append((key, value))
            on_done(self.fail_with)

    def flush(self, timeout: float = 0.0) -> int:
        self.poll()
        return 0

    def close(self) -> int:
        """As KafkaPublisher.close: what is still held is dropped, and nothing is delivered
        after; returns how many records were dropped."""
        dropped, self._pending = len(self._pending), []
        self.closed = True
        return dropped
