"""The demo history stores its incidents: what the rules find over the stored history (the
pose rules and the conflicts'), written through the processors' incidents port, found span by
span as over the whole; the processors' rebuild over the week's end finds the same."""

from __future__ import annotations

from collections import Counter

import pytest

from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.event_incidents import detect_all
from mapservice.local import demo_incidents
from mapservice.local.demo_history import backfill
from mapservice.processors.incident_watch import READ_LIMIT, EventSources, IncidentWatch
from mapservice.robot import DEFAULT_MAP
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000
HOURS = 4


@pytest.fixture(scope="module", params=[3, 9])
def week(request, monkeypatch_module):
    """Four hours of three robots in the memory store, found in one-hour spans (so that
    incidents cross spans)."""
    monkeypatch_module.setattr(demo_incidents, "SPAN_MS", 3_600_000)
    store = MemoryStore()
    result = backfill(
        store,
        load_ros_map(DEFAULT_MAP),
        days=HOURS / 24,
        robots=3,
        now_ms=NOW,
        conflict_window_ms=60_000,
        seed=request.param,
    )
    return store, result


@pytest.fixture(scope="module")
def monkeypatch_module():
    with pytest.MonkeyPatch.context() as patch:
        yield patch


def test_the_stored_incidents_are_what_the_rules_find_in_the_stored_history(week) -> None:
    store, result = week
    poses = store.poses(0, NOW + 60_000, limit=READ_LIMIT)
    records = EventSources(store, store, store, store).read(0, NOW + 60_000, None)
    expected = detect_all(poses, records, NOW)
    stored = store.incidents(0, NOW + 1, limit=100_000)
    assert sorted(stored, key=lambda i: i.incident_id) == sorted(
        expected, key=lambda i: i.incident_id
    )
    kinds = Counter(i.kind for i in stored)
    assert {"stuck", "offline", "battery_low", "near_miss", "conflict"} <= set(kinds), kinds
    assert result.incidents == len(stored)


def test_the_processors_rebuild_over_the_weeks_end_changes_nothing(week) -> None:
    """Started right after the backfill, the live detection finds the stored incidents
    again: nothing retracted, no incident of its own."""
    store, _ = week
    watch = IncidentWatch(
        Settings(),
        store,
        store,
        store,
        lambda: NOW,
        EventSources(store, store, store, store),
    )
    watch.load(NOW + 1)
    found, retracted = watch.tracker.take()
    more_found, more_retracted = watch.events.take()
    assert not retracted and not more_retracted
    stored = {i.incident_id: i for i in store.incidents(0, NOW + 1, limit=100_000)}
    assert [i for i in (*found, *more_found) if stored.get(i.incident_id) != i] == []
