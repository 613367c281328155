"""The machine yardstick: a fixed piece of work timed before each bench run."""

from __future__ import annotations

import pytest

from mapservice.bench import yardstick


def test_the_yardstick_times_its_set_piece_in_milliseconds_and_slows_with_more_work(monkeypatch) -> None:
    """A positive median; a round made three times longer reads about three times as long."""
    base = yardstick.yardstick_ms(rounds=3)
    assert base > 0
    one = yardstick._one_round
    monkeypatch.setattr(yardstick, "_one_round", lambda: [one() for _ in range(3)][0])
    assert yardstick.yardstick_ms(rounds=3) > 2 * base


def test_the_yardstick_refuses_zero_rounds() -> None:
    """No rounds is a caller's error, said plainly, not a median of nothing."""
    with pytest.raises(ValueError, match="at least 1"):
        yardstick.yardstick_ms(rounds=0)


def test_the_ingest_results_show_the_yardstick(capsys) -> None:
    """A run's yardstick appears in the result table, so two runs' machines can be compared."""
    import argparse

    from rich.console import Console

    from mapservice.bench.ingest import print_results
    from tests.mapservice.bench.test_ingest import _fleet_figures

    med = {**_fleet_figures(), "offered_events_per_s": 1200.0, "published_events_per_s": 1200.0,
           "stats_poses_minus_expected": 0, "stats_chunk_events_minus_expected": 0,
           "dead_letters": 0, "latency_censored": 0, "published_events": 72_000,
           "bytes_per_robot_day": 2e6, "storage.bytes_per_robot_day_events_only": 1e6,
           "yardstick_ms": 18.25}
    args = argparse.Namespace(robots=1000, seconds=60.0, mqtt="mosquitto", poll_interval=0.1)
    facts = {"nproc": 2, "cpu_model": "x", "ram_bytes": 2**30, "python": "3", "tansu": "t",
             "mosquitto": "m"}
    print_results(Console(width=200), args, facts, [med], med)
    line = next(l for l in capsys.readouterr().out.splitlines() if "machine yardstick" in l)
    assert "18.2" in line
