"""The live views' clock for silences: the wall clock less how far behind the stream the
newest stored batch was; never turned back, never ahead of the wall clock."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from mapservice.processors.stream_clock import StreamClock
from tests.conftest import pose_event

# steps: (wall ms advanced, the batch's events' receive times before the wall, or an idle poll)
steps = st.lists(
    st.tuples(
        st.integers(0, 5_000),
        st.one_of(st.none(), st.lists(st.integers(-500, 120_000), min_size=1, max_size=5)),
    ),
    max_size=60,
)


@given(steps)
def test_the_clock_is_the_wall_less_the_newest_batch_lag_and_never_goes_back(steps) -> None:
    wall = [1_795_255_200_000]
    clock = StreamClock(lambda: wall[0])
    said = []
    behind = 0
    for advance, ages in steps:
        wall[0] += advance
        if ages is None:
            clock.caught_up()
            behind = 0
        else:
            clock.stored([pose_event("r", wall[0] - a - 40, receive_lag_ms=40) for a in ages])
            behind = max(0, min(ages))
        said.append(clock.now_ms())
        assert said[-1] <= wall[0]
        assert said[-1] >= wall[0] - behind
        if said[-1] > wall[0] - behind:  # held: an earlier reading was later
            assert said[-1] == max(said[:-1])
    assert said == sorted(said)
