"""`mapservice bench ingest --kafka both`: rounds alternate the brokers, the table compares
each measure per broker with Apache Kafka's over tansu's ratio."""

from __future__ import annotations

import argparse
from argparse import Namespace

import pytest

from mapservice.bench.brokers import ratio, run_rounds, side_by_side
from mapservice.bench.cli import add_bench_parser


class Quiet:
    def print(self, *_a, **_k) -> None:
        pass


def test_each_round_runs_both_brokers_alternating_which_goes_first(tmp_path) -> None:
    """Two rounds: apache then tansu, then tansu then apache; each run gets its broker and
    its own data dir, and its result is filed under that broker."""
    calls = []

    def fake_run_once(args, run_dir, i, runs, console):
        calls.append((args.kafka, run_dir.relative_to(tmp_path).as_posix(), i))
        return {"lost": 0, "duplicated": 0, "latency_p99_s": 1.0, "loadavg_1min_after_fleet": 0.5}

    args = Namespace(repeat=2, robots=10, seconds=5, mqtt="mosquitto", kafka="both")
    runs = run_rounds(args, tmp_path, Quiet(), fake_run_once)
    assert calls == [
        ("apache", "apache/run-1", 1),
        ("tansu", "tansu/run-1", 1),
        ("tansu", "tansu/run-2", 2),
        ("apache", "apache/run-2", 2),
    ]
    assert [r["broker"] for r in runs["apache"]] == ["apache", "apache"]
    assert all(len(r["loadavg_before_run"]) == 3 for r in runs["tansu"])


def test_side_by_side_takes_each_brokers_medians_and_the_ratio() -> None:
    """CPU per event of the broker, latency and memory come from each broker's medians;
    the ratio is Apache Kafka's over tansu's, None where a side is missing or zero."""
    med = {
        "apache": {
            "cpu_us_per_event.kafka": 30.0,
            "latency_p99_s": 0.8,
            "rss_mb_after_fleet.kafka": 400.0,
            "lost": 0.0,
        },
        "tansu": {
            "cpu_us_per_event.kafka": 20.0,
            "latency_p99_s": 0.4,
            "rss_mb_after_fleet.kafka": 100.0,
            "lost": 0.0,
        },
    }
    rows = dict(side_by_side(med))
    assert rows["CPU per event: kafka (µs)"] == {"apache": 30.0, "tansu": 20.0}
    assert ratio(rows["CPU per event: kafka (µs)"]) == pytest.approx(1.5)
    assert ratio(rows["latency publish -> queryable p99 (s)"]) == pytest.approx(2)
    assert ratio(rows["memory: kafka (MB resident)"]) == pytest.approx(4)
    assert ratio(rows["lost"]) is None  # 0 on tansu: no ratio
    assert rows["memory: gateway (MB resident)"] == {"apache": None, "tansu": None}


def test_the_ingest_command_takes_kafka_both_with_help() -> None:
    """`bench ingest --kafka both` parses; an unknown broker is refused."""
    parser = argparse.ArgumentParser()
    add_bench_parser(parser.add_subparsers(dest="command"))
    assert parser.parse_args(["bench", "ingest", "--kafka", "both"]).kafka == "both"
    assert parser.parse_args(["bench", "ingest"]).kafka == "auto"
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "ingest", "--kafka", "redpanda"])
