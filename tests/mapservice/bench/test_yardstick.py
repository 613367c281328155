"""The machine yardstick: a fixed piece of work timed before each bench run."""

from __future__ import annotations

import pytest

from mapservice.bench import yardstick


def test_the_yardstick_is_the_median_of_its_timed_rounds_after_one_untimed_warm_up(
    monkeypatch,
) -> None:
    """Rounds of 5, 1 and 3 ms read 3 ms; the set piece runs four times (warm-up first)."""
    ran: list[int] = []
    monkeypatch.setattr(yardstick, "_one_round", lambda: ran.append(1) or 0)
    clock = iter([0.0, 0.005, 1.0, 1.001, 2.0, 2.003])  # (start, end) of each timed round
    assert yardstick.yardstick_ms(rounds=3, clock=lambda: next(clock)) == pytest.approx(3.0)
    assert len(ran) == 4


def test_the_set_piece_does_the_same_work_every_round() -> None:
    """Its checksum repeats: every round is the same work, so rounds are comparable."""
    assert yardstick._one_round() == yardstick._one_round() > 0


def test_the_yardstick_refuses_zero_rounds() -> None:
    """No rounds is a caller's error, said plainly, not a median of nothing."""
    with pytest.raises(ValueError, match="at least 1"):
        yardstick.yardstick_ms(rounds=0)
