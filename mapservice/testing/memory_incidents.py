"""The memory store's incidents: each incident's latest finding, as ClickHouse's
`incidents` table read with FINAL keeps it (mapservice/adapters/clickhouse/incident_schema.py)."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from mapservice.core.incident_model import meets
from mapservice.core.incidents import Incident


class IncidentLog:
    def __init__(self) -> None:
        # id -> (found_ms, retracted, incident): the latest finding
        self._latest: dict[str, tuple[int, bool, Incident]] = {}
        self._lock = threading.Lock()

    def append(
        self, found: Sequence[Incident], found_ms: int, retracted: Sequence[Incident]
    ) -> None:
        with self._lock:
            for incidents, gone in ((found, False), (retracted, True)):
                for incident in incidents:
                    before = self._latest.get(incident.incident_id)
                    # As ReplacingMergeTree(found): the later finding, on a tie the later insert
                    if before is None or found_ms >= before[0]:
                        self._latest[incident.incident_id] = (found_ms, gone, incident)

    def incidents(
        self,
        from_ms: int,
        to_ms: int,
        kinds: Sequence[str] = (),
        robot_id: str | None = None,
        limit: int = 10_000,
    ) -> list[Incident]:
        with self._lock:
            found = [
                i
                for _, gone, i in self._latest.values()
                if not gone
                and meets(i, from_ms, to_ms)
                and (not kinds or i.kind in kinds)
                and (robot_id is None or robot_id in i.robots)
            ]
        return sorted(found, key=lambda i: (i.start_ms, i.kind, i.incident_id))[:limit]

    def forget_before(self, cut_ms: int) -> None:
        """The retention: the incidents that began before `cut_ms` (a day's start) go."""
        with self._lock:
            self._latest = {k: v for k, v in self._latest.items() if v[2].start_ms >= cut_ms}
