"""The store contract, incidents per cell (`IncidentReader.incidents_per_cell`), what the
incidents heatmap shows: the counts of the first `limit` incidents the list gives for a
span, placed by heatmaps.incident_cells (the place rounded half to even to the millimetre,
floored to the cell), counted inside the store without reading the incidents themselves.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py. The constructed tests place incidents on the roundings' ties
and the cells' edges; the generated one compares the store with the rule applied to its own
list on random incidents, windows, cell sizes and limits.
"""

from __future__ import annotations

import itertools

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.heatmaps import count_incidents
from mapservice.core.incidents import Incident, PoseRef, incident_id

_examples = itertools.count()


def _at(t0: int, x: float, y: float, start=0, end=1_000, kind="near_miss", robot="r1", **more):
    fields = {
        "incident_id": incident_id(kind, (robot,), t0 + start),
        "kind": kind,
        "robots": (robot,),
        "start_ms": t0 + start,
        "end_ms": t0 + end,
        "ongoing": False,
        "x": x,
        "y": y,
        "severity": "warning",
        "measure": 0.5,
        "evidence": (PoseRef(robot, t0 + start, x, y),),
    }
    return Incident(**{**fields, **more})


def test_incidents_are_counted_in_the_cell_of_their_place(store, t0) -> None:
    rows = [
        # -0.5 mm rounds half to even to 0 (cell 0), not away from zero (cell -1)
        _at(t0, -0.0005, 0.1, robot="a"),
        # 499.5 mm rounds to 500: cell 1, not the 0 of a truncation
        _at(t0, 0.4995, 0.1, robot="b"),
        # -500.5 mm rounds to -500: cell -1; -0.2 m floors to cell -1, not 0
        _at(t0, -0.5005, -0.2, robot="c"),
        _at(t0, -0.2, -0.2, robot="d"),
        _at(t0, 1.7, 2.3, robot="e", start=2_000, end=2_000),
    ]
    store.append_incidents(rows, t0 + 10_000)
    assert store.incidents_per_cell(t0, t0 + 10_000, 1) == (
        {(0, 0): 1, (1, 0): 1, (-1, -1): 2, (3, 4): 1},
        False,
    )
    # 1.5 m cells: the finest (1, 0) and (0, 0) are one cell, (3, 4) is (1, 1)
    assert store.incidents_per_cell(t0, t0 + 10_000, 3) == (
        {(0, 0): 2, (-1, -1): 2, (1, 1): 1},
        False,
    )
    # the window: those meeting [1001, 3000) are e only
    assert store.incidents_per_cell(t0 + 1_001, t0 + 3_000, 1) == ({(3, 4): 1}, False)
    with pytest.raises(ValueError):
        store.incidents_per_cell(t0, t0 + 10_000, 0)


def test_only_the_listed_incidents_count(store, t0) -> None:
    """Retracted ones and those ended before the window are left out; an ongoing one whose
    stored end lies before the window counts (the list's rule)."""
    gone = _at(t0, 0.1, 0.1, robot="gone")
    store.append_incidents(
        [
            gone,
            _at(t0, 0.1, 0.1, robot="ended", end=4_999),
            _at(t0, 0.6, 0.1, robot="going", kind="offline", end=1_000, ongoing=True),
            _at(t0, 1.1, 0.1, robot="inside", start=6_000, end=7_000),
        ],
        t0 + 8_000,
    )
    store.append_incidents([], t0 + 9_000, retracted=[gone])
    assert store.incidents_per_cell(t0 + 5_000, t0 + 10_000, 1) == ({(1, 0): 1, (2, 0): 1}, False)


def test_the_first_incidents_of_the_list_count_and_the_rest_are_told(store, t0) -> None:
    """Over the limit: the first `limit` by start, kind and id count, and truncated says
    more met the span; exactly `limit` is no truncation."""
    rows = [
        _at(t0, 0.5 * k, 0.0, start=1_000 * (4 - k), end=10_000, robot=f"r{k}") for k in range(5)
    ]
    store.append_incidents(rows, t0 + 11_000)
    # by start: r4 (x 2.0: cell 4), r3 (cell 3), r2 (cell 2), ...
    assert store.incidents_per_cell(t0, t0 + 11_000, 1, limit=3) == (
        {(4, 0): 1, (3, 0): 1, (2, 0): 1},
        True,
    )
    assert store.incidents_per_cell(t0, t0 + 11_000, 1, limit=4)[1] is True
    assert store.incidents_per_cell(t0, t0 + 11_000, 1, limit=5) == (
        {(k, 0): 1 for k in range(5)},
        False,
    )


# Places on a small floor in half millimetres (ties of the rounding), some the same cell.
_place = st.integers(-3000, 3000).map(lambda half_mm: half_mm / 2000)
_incident = st.tuples(
    _place,
    _place,
    st.integers(0, 60_000),  # start
    st.integers(0, 30_000),  # length
    st.sampled_from(["near_miss", "stuck", "offline"]),
    st.booleans(),  # ongoing
)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    incidents=st.lists(_incident, min_size=1, max_size=40),
    window=st.tuples(st.integers(0, 90_000), st.integers(1, 90_000)),
    factor=st.sampled_from([1, 2, 3, 40]),
    limit=st.integers(1, 45),
)
def test_the_counts_are_the_rule_over_the_list(store, t0, incidents, window, factor, limit):
    example = next(_examples)
    base = t0 - 5 * 3_600_000 + example * 200_000  # a span of its own: examples share the store
    rows = [
        _at(base, x, y, start, start + length, kind, f"g{example}-{n}", ongoing=ongoing)
        for n, (x, y, start, length, kind, ongoing) in enumerate(incidents)
    ]
    store.append_incidents(rows, base + 100_000)
    f, t = base + window[0], base + window[0] + window[1]
    listed = store.incidents(f, t, limit=limit + 1)
    assert store.incidents_per_cell(f, t, factor, limit) == count_incidents(listed, factor, limit)
