"""The pose columns a batch inserts hold, value for value, what `mm` and `flag` make of each
pose: the batch conversion (numpy, for speed) rounds every millimetre as `round` does,
halves to even included, and a value numpy cannot hold exactly fails as `mm` fails."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.adapters.clickhouse.connection import flag, mm
from mapservice.adapters.clickhouse.writes import POSE_INSERT_COLUMNS, _pose_columns
from mapservice.core.events import PoseReported, make_envelope

# Metres near millimetre halves (x.xxx5, where rounding ties are likeliest), ordinary
# metres, integers, and far beyond any floor.
metres = st.one_of(
    st.integers(-200_000, 200_000).map(lambda n: (n + 0.5) / 1000),
    st.floats(-1e6, 1e6, allow_nan=False),
    st.integers(-1000, 1000),
    st.floats(-1e14, 1e14, allow_nan=False),
)
point = st.tuples(metres, metres)
flags = st.sampled_from([True, False, None, "yes", ""])
poses = st.builds(
    PoseReported,
    st.tuples(metres, metres, metres),
    st.just((0.0, 0.0, 0.38, 0.92)),
    st.one_of(st.none(), st.floats(0, 100)),
    flags,
    flags,
    st.one_of(st.none(), st.lists(point, max_size=12).map(tuple)),
)


def _row(t_ms: int, p: PoseReported) -> list:
    """The row as the columns must hold it, value by value."""
    path = p.path or ()
    return [
        "r1",
        t_ms,
        mm(p.position[0]),
        mm(p.position[1]),
        mm(p.position[2]),
        *p.orientation,
        p.battery_level,
        flag(p.charging),
        flag(p.loaded),
        p.path is not None,
        [mm(x) for x, _ in path],
        [mm(y) for _, y in path],
        25,
    ]


@settings(max_examples=200, deadline=None)
@given(st.lists(poses, min_size=1, max_size=20))
def test_the_columns_hold_each_poses_values_in_millimetres(batch) -> None:
    events = [make_envelope("r1", 1000 + i, 1025 + i, p) for i, p in enumerate(batch)]
    columns = _pose_columns(events)
    assert len(columns) == len(POSE_INSERT_COLUMNS)
    rows = [list(row) for row in zip(*columns)]
    expected = [_row(1000 + i, p) for i, p in enumerate(batch)]
    assert rows == expected
    for got, want in zip(rows, expected):
        assert [type(v) for v in got] == [type(v) for v in want]


@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan])
def test_a_value_mm_cannot_round_fails_as_mm_fails(bad) -> None:
    pose = PoseReported((1.0, 2.0, 0.0), (0.0, 0.0, 0.0, 1.0), 50.0, path=((0.5, bad),))
    with pytest.raises((ValueError, OverflowError)):
        mm(bad)
    with pytest.raises((ValueError, OverflowError)):
        _pose_columns([make_envelope("r1", 1, 2, pose)])
