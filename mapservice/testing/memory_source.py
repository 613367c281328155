"""In-memory EventSource for tests: a log with committed offsets and re-delivery."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from mapservice.core.ports import SourceRecord


class MemorySource:
    def __init__(self) -> None:
        self.log: list[SourceRecord] = []
        self.committed: dict[tuple[str, int], int] = {}  # next offset to read
        self.position = 0
        self.started = False
        self.fail_commits = False
        self._lock = threading.Lock()

    def append(self, topic: str, value: bytes, partition: int = 0) -> SourceRecord:
        with self._lock:
            offset = sum(1 for r in self.log if (r.topic, r.partition) == (topic, partition))
            record = SourceRecord(topic, partition, offset, value)
            self.log.append(record)
            return record

    def start(self) -> None:
        self.started = True

    def poll(self, max_records: int, timeout_s: float) -> list[SourceRecord]:
        with self._lock:
            batch = self.log[self.position:self.position + max_records]
            self.position += len(batch)
            return batch

    def commit(self, records: Sequence[SourceRecord]) -> bool:
        if self.fail_commits:
            return False
        with self._lock:
            for r in records:
                key = (r.topic, r.partition)
                self.committed[key] = max(self.committed.get(key, 0), r.offset + 1)
        return True

    def restart(self) -> None:
        """As a new consumer would: resume from the committed offsets."""
        with self._lock:
            self.position = next(
                (i for i, r in enumerate(self.log)
                 if r.offset >= self.committed.get((r.topic, r.partition), 0)), len(self.log))

    def close(self) -> None:
        self.started = False
