"""How a run found earlier and its continuation found over later poses make one run, as the
rules find the whole of it (incidents.py, near_miss.py): the live detection carries runs
that go on from what it found before instead of judging them again from their start."""

from __future__ import annotations

from collections.abc import Callable

import msgspec

from mapservice.core.incident_model import STUCK_CRITICAL_S, Incident, IncidentThresholds
from mapservice.core.near_miss import Closest


def joined_own(before: Incident, after: Incident, th: IncidentThresholds) -> Incident:
    """A run found ongoing (`before`) and its part from the poses before the new ones on
    (`after`, found over them and the new ones) as one, as the rules find the whole run."""
    if before.kind == "stuck":
        still_s = (after.end_ms - before.start_ms) / 1000
        return msgspec.structs.replace(
            after,
            incident_id=before.incident_id,
            start_ms=before.start_ms,
            measure=still_s,
            severity="critical" if still_s >= STUCK_CRITICAL_S else "warning",
            evidence=(before.evidence[0], after.evidence[1]),
            from_data_edge=False,
        )
    low = min(before, after, key=lambda i: (i.measure, i.evidence[1].ts_ms))
    return msgspec.structs.replace(
        after,
        incident_id=before.incident_id,
        start_ms=before.start_ms,
        x=low.x,
        y=low.y,
        measure=low.measure,
        severity=low.severity,
        evidence=(before.evidence[0], low.evidence[1]),
        from_data_edge=False,
    )


def join_runs(
    before: Incident,
    before_closest: Closest,
    after: Incident,
    after_closest: Closest,
    first_tick: int,
) -> tuple[Incident, Closest]:
    """A run found earlier (`before`) and its continuation found over the ticks from
    `first_tick` on (`after`, starting at most a tick after `before` ends; the two may
    share a tick) as the rule finds the whole run: its start, id and data edge from
    `before`, its end and whether it goes on from `after`, its figures from the closer of
    the two closest ticks (the earlier of equal ones). A closest tick of `before` at or
    after `first_tick` was judged again in `after`: a tick on a robot's newest pose is
    placed from the pose before it until a later one comes (the same place, the last bit
    aside, but other evidence), and every earlier tick of `before` was farther."""
    if before_closest.tick_ms >= first_tick or after_closest < before_closest:
        best, figures = after_closest, after
    else:
        best, figures = before_closest, before
    return (
        msgspec.structs.replace(
            after,
            incident_id=before.incident_id,
            start_ms=before.start_ms,
            from_data_edge=before.from_data_edge,
            x=figures.x,
            y=figures.y,
            severity=figures.severity,
            measure=figures.measure,
            evidence=figures.evidence,
        ),
        best,
    )


def carried_on(
    joinable: dict[tuple[str, ...], Incident],
    known_closest: dict[str, Closest],
    fresh: list[Incident],
    fresh_closest: dict[str, Closest],
    first_tick: int,
    tick_ms: int,
    newest_ms: Callable[[str], int],
) -> tuple[list[Incident], dict[str, Closest]]:
    """The runs found over the ticks from `first_tick` on (`fresh`), with the runs of
    `joinable` (one per pair: begun before `first_tick`, over ticks that cannot change)
    carried on by the fresh run of their pair that begins at `first_tick`; a joinable run
    that none carries on ended before it, unchanged but for whether it goes on (a later
    tick may still lack one of its robots' positions). Every result's closest tick too."""
    found, closest = [], {}
    joined = set()
    for run in fresh:
        figures = fresh_closest[run.incident_id]
        before = joinable.get(run.robots)
        if before is not None and run.start_ms == first_tick:
            run, figures = join_runs(
                before, known_closest[before.incident_id], run, figures, first_tick
            )
            joined.add(run.robots)
        found.append(run)
        closest[run.incident_id] = figures
    for pair, before in joinable.items():
        if pair not in joined:
            going_on = before.end_ms + tick_ms > min(newest_ms(r) for r in pair)
            found.append(msgspec.structs.replace(before, ongoing=going_on))
            closest[before.incident_id] = known_closest[before.incident_id]
    return found, closest
