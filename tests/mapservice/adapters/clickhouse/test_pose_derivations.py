"""derive_views re-reads a live batch's stored poses inside ClickHouse instead of sending its
rows again; a backlog, scattered late poses and a cluster send the rows. Either way the pose
views end up the same."""

from __future__ import annotations

import time

import pytest

from mapservice.adapters.clickhouse.writes import (
    REREAD_GAP_MS,
    REREAD_MAX_MS,
    REREAD_MAX_SPANS,
    reread_spans,
)
from tests.conftest import clone_migrated, pose_event


@pytest.fixture
def store(open_store, chdb_dir):
    """A new migrated database in the module's chDB (tests/conftest.py)."""
    s = open_store("clickhouse")
    clone_migrated(chdb_dir, s.database)
    s.migrate()
    yield s
    s.close()


def _m0() -> int:
    hour_ago = int(time.time() * 1000) - 3_600_000  # inside the retention
    return hour_ago - hour_ago % 60_000


def test_a_live_batch_is_one_span() -> None:
    # Five robots at 5 Hz for one second, unordered as a batch arrives.
    times = [1_000_000 + 200 * k + r for k in range(5) for r in range(5)][::-1]
    assert reread_spans(times) == [(1_000_000, 1_000_804)]


def test_event_times_further_apart_than_the_gap_are_spans_of_their_own() -> None:
    late = 1_000_000 - 60_000
    times = [1_000_000, 1_000_500, late, 1_000_500 + REREAD_GAP_MS + 1]
    assert reread_spans(times) == [
        (late, late),
        (1_000_000, 1_000_500),
        (1_000_500 + REREAD_GAP_MS + 1, 1_000_500 + REREAD_GAP_MS + 1),
    ]


def test_a_backlog_or_scattered_late_poses_are_not_re_read() -> None:
    # A robot's buffered minute, one pose a second: re-reading it would read every robot's minute.
    assert reread_spans([1_000_000 + 1_000 * s for s in range(60)]) is None
    assert reread_spans([0, REREAD_MAX_MS + 1]) == [(0, 0), (REREAD_MAX_MS + 1, REREAD_MAX_MS + 1)]
    # Two spans, of 1 s and of the rest of the limit (in steps of half a second), and 1 ms more.
    first = [0, 500, 1_000]
    second = list(
        range(2_500 + REREAD_GAP_MS, 2_500 + REREAD_GAP_MS + REREAD_MAX_MS - 1_000 + 1, 500)
    )
    assert len(reread_spans(first + second)) == 2
    assert reread_spans(first + second + [second[-1] + 1]) is None
    scattered = [10 * REREAD_GAP_MS * k for k in range(REREAD_MAX_SPANS + 1)]
    assert reread_spans(scattered) is None
    assert reread_spans(scattered[:-1]) is not None
    assert reread_spans([]) is None


def _rows_sent(store, monkeypatch) -> list[int]:
    """Counts the rows derive_views sends to pose_derivations from Python."""
    sent: list[int] = []
    insert = store.connection.insert

    def counting(table, rows, columns, *, column_oriented=False):
        if table == "pose_derivations":
            sent.append(len(rows[0]) if column_oriented else len(rows))
        return insert(table, rows, columns, column_oriented=column_oriented)

    monkeypatch.setattr(store.connection, "insert", counting)
    return sent


def test_a_live_batch_is_derived_from_its_stored_poses_without_sending_its_rows(
    store, monkeypatch
) -> None:
    m0 = _m0()
    batch = [pose_event(f"r{r}", m0 + 200 * k + r, x=float(k)) for k in range(5) for r in range(3)]
    store.append_events(batch)
    # Stored, not derived yet: neither the track nor the minutes' view has it.
    assert store.robot_track("r1", m0, m0 + 60_000) == []
    assert [b.robots_active for b in store.timeline(m0, m0 + 60_000, 1)] == [0]
    sent = _rows_sent(store, monkeypatch)
    store.derive_views(batch)
    store.derive_views(batch)  # re-delivered: once
    assert sent == []
    assert [p.x for p in store.robot_track("r1", m0, m0 + 60_000)] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert [b.robots_active for b in store.timeline(m0, m0 + 60_000, 1)] == [3]


def test_a_backlog_and_a_cluster_send_the_rows(store, monkeypatch) -> None:
    m0 = _m0()
    backlog = [pose_event("r1", m0 + 1_000 * s, x=float(s)) for s in range(30)]
    store.append_events(backlog)
    sent = _rows_sent(store, monkeypatch)
    store.derive_views(backlog)
    assert sent == [30]
    assert [p.x for p in store.robot_track("r1", m0, m0 + 60_000)] == [float(s) for s in range(30)]
    live = [pose_event("r2", m0 + 40_000 + 200 * k, x=float(k)) for k in range(5)]
    store.append_events(live)
    monkeypatch.setattr(store.connection, "cluster", "replicated")
    store.derive_views(live)
    assert sent == [30, 5]
    assert len(store.robot_track("r2", m0, m0 + 60_000)) == 5
