"""`mapservice bench ingest --kafka both` and `--compare A --compare B`: rounds alternate the
variants, the table compares each measure per variant with a ratio; a variant's settings,
broker and Python reach the stack it runs."""

from __future__ import annotations

import argparse
import sys
from argparse import Namespace

import pytest

from mapservice.bench.cli import add_bench_parser
from mapservice.bench.compare import (
    BROKER_VARIANTS,
    Variant,
    ratio,
    run_rounds,
    side_by_side,
    variants_of,
)


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
    runs = run_rounds(args, BROKER_VARIANTS, tmp_path, Quiet(), fake_run_once)
    assert calls == [
        ("apache", "apache/run-1", 1),
        ("tansu", "tansu/run-1", 1),
        ("tansu", "tansu/run-2", 2),
        ("apache", "apache/run-2", 2),
    ]
    assert [r["variant"] for r in runs["apache"]] == ["apache", "apache"]
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
    rows = dict(side_by_side(med, ("apache", "tansu")))
    assert rows["CPU per event: kafka (µs)"] == {"apache": 30.0, "tansu": 20.0}
    assert ratio(rows["CPU per event: kafka (µs)"], "apache", "tansu") == pytest.approx(1.5)
    assert ratio(rows["latency publish -> queryable p99 (s)"], "apache", "tansu") == pytest.approx(
        2
    )
    assert ratio(rows["memory: kafka (MB resident)"], "apache", "tansu") == pytest.approx(4)
    assert ratio(rows["lost"], "apache", "tansu") is None  # 0 on tansu: no ratio
    assert rows["memory: gateway (MB resident)"] == {"apache": None, "tansu": None}


def test_the_ingest_command_takes_kafka_both_with_help() -> None:
    """`bench ingest --kafka both` parses; an unknown broker is refused."""
    parser = argparse.ArgumentParser()
    add_bench_parser(parser.add_subparsers(dest="command"))
    assert parser.parse_args(["bench", "ingest", "--kafka", "both"]).kafka == "both"
    assert parser.parse_args(["bench", "ingest"]).kafka == "auto"
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "ingest", "--kafka", "redpanda"])


def test_compared_variants_run_interleaved_with_their_settings_broker_and_python(tmp_path) -> None:
    """Three rounds of two variants: A B, B A, A B; each run's stack gets its variant's
    settings, broker (or the command's) and Python; the ratio puts B's figure over A's."""
    python = tmp_path / "python"
    python.write_text("#!/bin/sh\n")
    python.chmod(0o755)
    args = Namespace(
        repeat=3,
        robots=10,
        seconds=5,
        mqtt="mosquitto",
        kafka="auto",
        compare=[f"main=python={python}", "wait50=MAPSERVICE_KAFKA_FETCH_WAIT_MS=50,kafka=tansu"],
    )
    (a, b), over, under = variants_of(args)
    assert (a.python, a.env, a.kafka) == (str(python), {}, None)
    assert (b.python, b.env, b.kafka) == (None, {"MAPSERVICE_KAFKA_FETCH_WAIT_MS": "50"}, "tansu")
    assert (over, under) == ("wait50", "main")
    calls = []

    def fake_run_once(run_args, run_dir, i, runs, console):
        calls.append(
            (
                run_dir.relative_to(tmp_path).as_posix(),
                run_args.kafka,
                run_args.stack_env,
                run_args.stack_python,
            )
        )
        return {
            "lost": 0,
            "duplicated": 0,
            "loadavg_1min_after_fleet": 0.5,
            "cpu_us_per_event": {"stack_total": 100.0 if run_args.stack_python else 40.0},
        }

    runs = run_rounds(args, (a, b), tmp_path / "runs", Quiet(), fake_run_once)
    assert [c[0] for c in calls] == [
        "runs/main/run-1",
        "runs/wait50/run-1",
        "runs/wait50/run-2",
        "runs/main/run-2",
        "runs/main/run-3",
        "runs/wait50/run-3",
    ]
    assert [c[1:] for c in calls if "main/" in c[0]] == [("auto", {}, str(python))] * 3
    assert [c[1:] for c in calls if "wait50/" in c[0]] == [
        ("tansu", {"MAPSERVICE_KAFKA_FETCH_WAIT_MS": "50"}, None)
    ] * 3
    from mapservice.bench.ingest.report import medians

    med = {name: medians(r) for name, r in runs.items()}
    rows = dict(side_by_side(med, ("main", "wait50")))
    assert ratio(rows["CPU per event: stack total (µs)"], over, under) == pytest.approx(0.4)


@pytest.mark.parametrize(
    "compare, error",
    [
        (None, "given twice"),
        (["a=X=1"], "given twice"),
        (["a=X=1", "b=X=2", "c=X=3"], "given twice"),
        (["a=X=1", "a=X=2"], "two names"),
        (["=X=1", "b=X=2"], "starts with its name"),
        (["a b=X=1", "b=X=2"], "starts with its name"),
        (["a=X", "b=X=2"], "is not KEY=VALUE"),
        (["a==1", "b=X=2"], "is not KEY=VALUE"),
        (["a=kafka=redpanda", "b=X=2"], "kafka is one of"),
        (["a=python=/nonexistent/python", "b=X=2"], "not an executable Python"),
    ],
)
def test_a_malformed_comparison_is_refused_saying_what_is_wrong(compare, error) -> None:
    args = Namespace(kafka="auto", compare=compare)
    with pytest.raises(SystemExit) as exit_:
        variants_of(args)
    assert error in str(exit_.value.code)


def test_a_stack_runs_its_components_with_the_python_it_is_given(tmp_path) -> None:
    """Another checkout's Python runs the components: the spawned command names it."""
    from mapservice.local.stack import Stack

    python = tmp_path / "python"
    python.write_text("#!/bin/sh\nsleep 30\n")
    python.chmod(0o755)
    stack = Stack(tmp_path / "data", python=str(python))
    proc = stack.spawn("gateway", "gateway")
    try:
        assert proc.args[0] == str(python)
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.parametrize("given", [False, True], ids=["this-python", "another-python"])
def test_a_checkout_in_the_working_directory_never_shadows_the_components_code(
    tmp_path, monkeypatch, given
) -> None:
    """`python -m` puts the working directory first on sys.path: a comparison run from one
    checkout would run that checkout's `mapservice` under the other checkout's Python, both
    variants the same code. The components import the installed package whatever the
    directory holds."""
    from mapservice.local.stack import Stack

    shadow = tmp_path / "checkout"
    (shadow / "mapservice").mkdir(parents=True)
    (shadow / "mapservice" / "__init__.py").write_text("")
    (shadow / "mapservice" / "cli.py").write_text("print('the working directory's code')\n")
    monkeypatch.chdir(shadow)
    stack = Stack(tmp_path / "data", python=sys.executable if given else "")
    proc = stack.spawn("gateway", "--help")
    assert proc.wait(timeout=60) == 0
    out = (stack.log_dir / "gateway.log").read_text()
    assert "the working directory's code" not in out
    assert "usage: mapservice" in out


def test_the_ingest_command_takes_two_comparisons_with_help() -> None:
    parser = argparse.ArgumentParser()
    add_bench_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["bench", "ingest", "--compare", "a=X=1", "--compare", "b=X=2"])
    assert args.compare == ["a=X=1", "b=X=2"]
    assert Variant.parse(args.compare[1]).env == {"X": "2"}
