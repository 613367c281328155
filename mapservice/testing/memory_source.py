"""In-memory EventSource for tests: a log with committed offsets, re-delivery and Kafka's
group-membership rule (the contract suite, tests/mapservice/adapters/test_source_contract.py,
holds it and KafkaBatchSource to the same behaviour)."""

from __future__ import annotations

import threading
from collections.abc import Sequence

import msgspec

from mapservice.core.ports import SourceRecord


class MemorySource:
    """One member of a consumer group that owns every partition of its log. The group can
    change under it (`rebalance`, `restart`): as with Kafka, records it delivered before the
    change are then not committed (`commit` returns False) and are delivered again."""

    def __init__(self) -> None:
        self.log: list[SourceRecord] = []
        self.committed: dict[tuple[str, int], int] = {}  # next offset to read
        self.position = 0
        self.started = False
        self.fail_commits = False
        self.membership = 0  # counts the group's changes (SourceRecord.membership)
        self.stays = 0  # calls of stay_in_group
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
            batch = self.log[self.position : self.position + max_records]
            self.position += len(batch)
            return [msgspec.structs.replace(r, membership=self.membership) for r in batch]

    def commit(self, records: Sequence[SourceRecord]) -> bool:
        """Commits past each partition's highest offset among `records` delivered in the
        current membership; False if any was delivered before the group changed (those are
        not committed, as KafkaBatchSource) or commits are set to fail."""
        if self.fail_commits:
            return False
        with self._lock:
            current = [r for r in records if r.membership == self.membership]
            for r in current:
                key = (r.topic, r.partition)
                self.committed[key] = max(self.committed.get(key, 0), r.offset + 1)
        return len(current) == len(records)

    def stay_in_group(self) -> None:
        """The twin's group never drops a member for a long pause: nothing to do but count."""
        self.stays += 1

    def rebalance(self) -> None:
        """The group changed (a member joined or left) and this member got its partitions
        back, as after Kafka's eager rebalance: a new membership, reading again from the
        committed offsets."""
        with self._lock:
            self.membership += 1
            self._rewind()

    def restart(self) -> None:
        """As a new consumer would: a new member, resuming from the committed offsets."""
        self.rebalance()

    def _rewind(self) -> None:
        self.position = next(
            (
                i
                for i, r in enumerate(self.log)
                if r.offset >= self.committed.get((r.topic, r.partition), 0)
            ),
            len(self.log),
        )

    def close(self) -> None:
        self.started = False
