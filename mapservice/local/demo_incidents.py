"""The demo history's incidents: what the processors' rules find over the stored week, found
the way a recomputation finds them (`detect_all`: the pose rules and the rules of the records
stored beside the poses, here the conflicts) and written where the processors write theirs
(`HistoryWriter.append_incidents`), so that the week's incidents panel, the incidents API
and the heatmap show them. The ids are the rules' own (kind, robots, start): when the
processors rebuild over the week's end they find the same incidents, not new ones.

The week is read a span at a time, each span with the history around it the rules need: an
incident is kept by the span its start falls in, found from poses reaching `before_ms`
earlier (so its start and the stuck window are judged on the whole history) and `after_ms`
later (so a run that began in the span ends where it really ends).
"""

from __future__ import annotations

from collections.abc import Callable

import structlog

from mapservice.core.event_incidents import detect_all
from mapservice.core.incident_model import Incident, IncidentThresholds
from mapservice.core.ports import HistoryStore
from mapservice.processors.incident_watch import READ_LIMIT, EventSources

log = structlog.get_logger(__name__)

SPAN_MS = 6 * 3_600_000
# Longer than any of the simulator's runs (a late charge's drive to a free charger is the
# longest, minutes): a run that began in a span ends inside this margin after it.
AFTER_MS = 3_600_000


def spans(start_ms: int, end_ms: int, span_ms: int = SPAN_MS) -> list[tuple[int, int]]:
    """[from, to) spans of at most `span_ms` covering [start_ms, end_ms]."""
    return [(a, min(a + span_ms, end_ms + 1)) for a in range(start_ms, end_ms + 1, span_ms)]


def incidents_in(
    store: HistoryStore,
    sources: EventSources,
    span: tuple[int, int],
    until_ms: int,
    th: IncidentThresholds,
) -> list[Incident]:
    """The incidents of the history known up to `until_ms` that start in `span`."""
    first, last = span
    before_ms = 2 * th.lookback_ms + th.tick_ms
    read_from, read_to = first - before_ms, min(last + AFTER_MS, until_ms + 1)
    poses = store.poses(read_from, read_to, limit=READ_LIMIT)
    records = sources.read(read_from, read_to, None)
    until = min(until_ms, read_to - 1)
    return [i for i in detect_all(poses, records, until, th) if first <= i.start_ms < last]


def store_incidents(
    store: HistoryStore,
    start_ms: int,
    until_ms: int,
    th: IncidentThresholds,
    progress: Callable[[float], None] | None = None,
) -> dict[str, int]:
    """Finds the incidents of the stored history [start_ms, until_ms] span by span and
    writes them, found at `until_ms`; returns how many of each kind."""
    sources = EventSources(store, store, store, store)
    counts: dict[str, int] = {}
    todo = spans(start_ms, until_ms)
    for n, span in enumerate(todo, 1):
        found = incidents_in(store, sources, span, until_ms, th)
        if found:
            store.append_incidents(found, until_ms)
        for incident in found:
            counts[incident.kind] = counts.get(incident.kind, 0) + 1
        if progress is not None:
            progress(n / len(todo))
    log.info("demo incidents written", total=sum(counts.values()), **counts)
    return counts
