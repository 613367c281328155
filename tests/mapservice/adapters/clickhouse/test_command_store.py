"""Both stores keep operators' commands and the robots' answers alike: one row per event
(a redelivery changes nothing), a window half-open and in time order, one robot's alone;
and they expire with the retention, as poses do (history, not state)."""

from __future__ import annotations

from mapservice.core.commands import (
    CommandAcknowledged,
    CommandFinished,
    CommandIssued,
    command_records,
)
from mapservice.core.events import PoseReported, make_envelope
from tests.conftest import NOW_MS, meta_event, sparse_snapshots

DAY_MS = 86_400_000
GOTO = CommandIssued(
    "c-2", "amr-2", "goto_poi", "operator:ab", NOW_MS + 10, "dock", 3.5, -1.25, 1.5
)


def _events(t: int = NOW_MS) -> list:
    return [
        make_envelope("amr-1", t, t, CommandIssued("c-1", "amr-1", "pause", "operator:ab", t)),
        make_envelope("amr-1", t + 300, t + 310, CommandAcknowledged("c-1", "amr-1", "accepted")),
        make_envelope(
            "amr-1", t + 900, t + 910, CommandFinished("c-1", "amr-1", "failed", "stuck")
        ),
        make_envelope("amr-2", NOW_MS + 10, NOW_MS + 10, GOTO),
    ]


def test_commands_and_answers_by_window_and_robot(store) -> None:
    events = _events()
    store.append(events)
    store.append(events[:2])  # a redelivery changes nothing
    got = store.command_events(NOW_MS, NOW_MS + 1_000)
    assert [(s.ts_ms, type(s.event).__name__) for s in got] == [
        (NOW_MS, "CommandIssued"),
        (NOW_MS + 10, "CommandIssued"),
        (NOW_MS + 300, "CommandAcknowledged"),
        (NOW_MS + 900, "CommandFinished"),
    ]
    assert [s.event for s in got] == [events[0].payload, GOTO, events[1].payload, events[2].payload]
    assert got[0].event_id == events[0].event_id
    assert store.command_events(NOW_MS + 1, NOW_MS + 900) == got[1:3]
    assert [s.event.command_id for s in store.command_events(NOW_MS, NOW_MS + 1_000, "amr-2")] == [
        "c-2"
    ]
    assert store.command_events(NOW_MS, NOW_MS + 1_000, limit=2) == got[:2]
    (first, second) = command_records(got)
    assert first.command.issued_by == "operator:ab" and first.ack[1].status == "accepted"
    assert first.outcome[1].reason == "stuck" and second.ack is None


def test_commands_expire_with_the_retention(store) -> None:
    """A week and a day later, the first day's commands are gone and the last day's stay."""
    later = NOW_MS + 8 * DAY_MS
    sparse_snapshots(store)  # tens of snapshots for these days, not a thousand
    pose = PoseReported((1.0, 2.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    store.append(
        [meta_event(NOW_MS - 1_000)]
        + [make_envelope("amr-1", NOW_MS + d * DAY_MS, NOW_MS + d * DAY_MS, pose) for d in range(9)]
        + _events(NOW_MS)
        + _events(later)[:3]
    )
    store.build_snapshots(later)
    store.apply_retention(later + 1_000)
    kept = store.command_events(NOW_MS - DAY_MS, later + DAY_MS)
    assert {s.ts_ms for s in kept} == {later, later + 300, later + 900}
