"""`mapservice bench ingest` end to end on a tiny fleet: its report is complete and honest."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

# Beside other modules' stacks in the parallel step: a tiny fleet, and the report is judged
# by its own accounts (every event stored once, stages that add up), not by absolute times.


@pytest.mark.timeout(600)
def test_bench_ingest_reports_zero_loss_latency_stages_and_storage(tmp_path) -> None:
    """Three robots for four seconds through Mosquitto: every event stored once and pushed
    live, the latency split at the gateway adds up, and storage is reported per table."""
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "bench",
            "ingest",
            "--robots",
            "3",
            "--seconds",
            "4",
            "--repeat",
            "1",
            "--mqtt",
            "mosquitto",
            "--data-dir",
            str(tmp_path / "data"),
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=540,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    run = json.loads(out.read_text())["runs"][0]
    assert run["published_events"] >= 3 * 4 and run["stored_events"] == run["published_events"]
    assert (run["lost"], run["duplicated"], run["dead_letters"]) == (0, 0, 0)
    assert run["live_errors"] == 0 and run["live_pushed_events"] == run["published_events"]
    assert run["latency_p99_s"] <= run["latency_polled_p99_s"]
    assert 0 <= run["publish_to_gateway_p50_s"] <= run["latency_p50_s"]
    assert 0 < run["gateway_to_queryable_p50_s"] <= run["latency_p99_s"]
    tables = run["storage"]["bytes_per_robot_day_by_table"]
    assert tables["poses"] > 0 and tables["chunk_events"] > 0 and tables["pose_keyframes"] > 0


@pytest.mark.timeout(600)
def test_bench_ingest_with_two_gateways_splits_the_load_and_accounts_for_every_message(
    tmp_path,
) -> None:
    """`--gateways 2`: both replicas take part through the shared subscription, their
    confirmed messages add up to exactly what the robots published, and nothing is lost.
    Without `--data-dir` the run's data goes to a temporary directory, removed at the end."""
    out = tmp_path / "bench.json"
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "bench",
            "ingest",
            "--robots",
            "3",
            "--seconds",
            "4",
            "--gateways",
            "2",
            "--mqtt",
            "mosquitto",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=540,
        env={**os.environ, "TMPDIR": str(temporary)},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(out.read_text())
    assert Path(doc["args"]["data_dir"]).parent == temporary
    assert not list(temporary.glob("mapservice-bench-*")), "the run's data was left behind"
    run = doc["runs"][0]
    assert run["gateways"] == 2 and (run["lost"], run["duplicated"]) == (0, 0)
    assert all(n > 0 for n in run["gateway_acked_by_replica"]), run["gateway_acked_by_replica"]
    assert run["gateway_acked_minus_published"] == 0
    assert "gateway-2" not in run["cpu_percent_of_one_core"]


@pytest.mark.timeout(600)
def test_bench_ingest_profile_writes_a_flame_graph_per_python_component(tmp_path) -> None:
    """`--profile DIR`: while the fleet runs, py-spy samples the gateway and `serve`; one flame
    graph each, named in the run's result (the brokers, not Python, get none)."""
    profiles = tmp_path / "profiles"
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "bench",
            "ingest",
            "--robots",
            "3",
            "--seconds",
            "4",
            "--mqtt",
            "mosquitto",
            "--no-latency-clients",
            "--profile",
            str(profiles),
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=540,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    run = json.loads(out.read_text())["runs"][0]
    assert run["profiles"] == {
        "gateway": str(profiles / "gateway-run1.svg"),
        "server": str(profiles / "server-run1.svg"),
    }
    assert sorted(p.name for p in profiles.iterdir()) == ["gateway-run1.svg", "server-run1.svg"]
    for svg in profiles.iterdir():
        assert re.search(r'id="frames"[^>]* total_samples="[1-9]', svg.read_text()), svg
