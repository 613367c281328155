"""The incidents of a loaded history, found after the load the way the processors find them:
the rules of mapservice/core/incidents.py (`detect`) over the stored poses, read through the
history reader's `poses` and written through the writer's `append_incidents`, as
processors/incident_watch.py reads and writes them. The history loader writes poses only,
so a benchmark of the incident reads finds them here first.

The poses are read a window at a time (an hour by default: 200 robots' hour is 720,000
poses, a day would be 17 M in memory at once). A window keeps the incidents that start
inside it; it is read from what the rules look back on before it (a stuck window, the
silence that may precede it, and one more silence, so a run that began before the window is
seen beginning there and left to the window before) to `margin_ms` after it, so that an
incident begun inside it is seen to its end. One that goes on past that margin is kept as
found there (counted in `cut`; its end and `ongoing` are then the margin's). The finding's
time (`found_ms`) is the end of what was read, as a live detection would have found it then.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from mapservice.core.incidents import IncidentThresholds, detect
from mapservice.core.ports import HistoryWriter, TimeTravelReader

HOUR_MS = 3_600_000
# Far more than a window's poses (200 robots x 1 h 11 min: 850,000); a window that holds
# more is refused rather than cut.
READ_LIMIT = 20_000_000


@dataclass
class FoundIncidents:
    """What finding a history's incidents took and found."""

    windows: int = 0
    poses_read: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)
    cut: int = 0  # went on past a window's right margin
    read_s: float = 0.0
    detect_s: float = 0.0
    write_s: float = 0.0
    window_ms: int = HOUR_MS
    margin_ms: int = 0

    @property
    def total(self) -> int:
        return sum(self.by_kind.values())


def find_incidents(
    history: TimeTravelReader,
    writer: HistoryWriter,
    start_ms: int,
    end_ms: int,
    *,
    window_ms: int = HOUR_MS,
    margin_ms: int | None = None,
    thresholds: IncidentThresholds | None = None,
    on_window: Callable[[int, int], None] | None = None,
) -> FoundIncidents:
    """Finds and writes the incidents that start in [start_ms, end_ms), the history known up
    to `end_ms`; `on_window(done, total)` after each window."""
    th = thresholds or IncidentThresholds()
    margin = max(th.lookback_ms, 600_000) if margin_ms is None else margin_ms
    if window_ms <= 0 or margin < 0:
        raise ValueError("the window must be positive and the margin not negative")
    before = th.lookback_ms + th.offline_after_ms
    out = FoundIncidents(window_ms=window_ms, margin_ms=margin)
    kinds: Counter[str] = Counter()
    total = -(-(end_ms - start_ms) // window_ms)
    for k in range(total):
        lo = start_ms + k * window_ms
        hi = min(end_ms, lo + window_ms)
        until = min(end_ms, hi + margin)
        t0 = time.perf_counter()
        poses = history.poses(lo - before, until, limit=READ_LIMIT + 1)
        if len(poses) > READ_LIMIT:
            raise ValueError(
                f"more than {READ_LIMIT:,} poses in [{lo - before}, {until}): use a shorter window"
            )
        t1 = time.perf_counter()
        kept = [i for i in detect(poses, until, th) if lo <= i.start_ms < hi]
        t2 = time.perf_counter()
        writer.append_incidents(kept, until)
        t3 = time.perf_counter()
        out.windows += 1
        out.poses_read += len(poses)
        out.cut += sum(1 for i in kept if i.ongoing and until < end_ms)
        kinds.update(i.kind for i in kept)
        out.read_s += t1 - t0
        out.detect_s += t2 - t1
        out.write_s += t3 - t2
        del poses
        if on_window is not None:
            on_window(k + 1, total)
    out.by_kind = dict(sorted(kinds.items()))
    return out


def find_or_reuse(chdb_dir: Path, database: str, start_ms: int, end_ms: int) -> dict[str, Any]:
    """The incidents of the history loaded into `database` of `chdb_dir`, found once: the
    record of the finding is kept beside the data (`incidents-<database>.json`) and read back
    on a reused directory. Opens the directory itself (the API process must not hold it)."""
    import json

    from mapservice.adapters.clickhouse.store import ClickHouseStore

    marker = chdb_dir.parent / f"incidents-{database}.json"
    if marker.exists():
        doc: dict[str, Any] = json.loads(marker.read_text())
        if (doc["start_ms"], doc["end_ms"]) == (start_ms, end_ms):
            return {**doc, "reused": True}
    store = ClickHouseStore(f"chdb://{chdb_dir.resolve()}", database=database)
    try:
        store.migrate()
        with store.lock:  # a finding cut short before: found again from nothing
            store.client.command(f"TRUNCATE TABLE {database}.incidents")

        def progress(done: int, total: int) -> None:
            if done == total or done % 12 == 0:
                print(f"bench ui: incidents {done}/{total} windows", file=sys.stderr, flush=True)

        found = find_incidents(store, store, start_ms, end_ms, on_window=progress)
        t0 = time.perf_counter()
        with store.lock:  # merged, as a long-running service's background merges leave it
            store.client.command(f"OPTIMIZE TABLE {database}.incidents FINAL")
        optimize_s = time.perf_counter() - t0
    finally:
        store.close()
    doc = {
        "start_ms": start_ms,
        "end_ms": end_ms,
        **asdict(found),
        "total": found.total,
        "optimize_s": round(optimize_s, 1),
    }
    marker.write_text(json.dumps(doc, indent=2))
    return {**doc, "reused": False}
