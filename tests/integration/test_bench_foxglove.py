"""`mapservice bench foxglove` end to end at a tiny size (three robots, two clients, three
seeks on a few minutes of history): its report is complete and sane, so the tool cannot
rot unnoticed. Judged by its own accounts (every pose reaches every client, each seek's
frame holds every robot), not by absolute times: other stacks run beside it."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.fixtures.npm import npm_installed
from tests.fixtures.paths import ROOT

pytestmark = pytest.mark.long  # a stack's start, a history's load and an API's: minutes


@pytest.mark.timeout(600)
def test_bench_foxglove_reports_cpu_per_message_latency_and_seek_frames(tmp_path) -> None:
    npm_installed(ROOT / "tests" / "foxglove_client", "to run Foxglove's own WebSocket client")
    out, data = tmp_path / "fox.json", tmp_path / "data"
    done = subprocess.run(
        [sys.executable, "-m", "mapservice.cli", "bench", "foxglove"]
        + ["--robots", "3", "--clients", "2", "--seconds", "6", "--baseline-seconds", "2"]
        + ["--kafka", "tansu", "--seeks", "3", "--days", "0.005", "--seek-robots", "3"]
        + ["--data-dir", str(data), "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=540,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads(out.read_text())
    live, seek = doc["live"], doc["seek"]
    assert doc["machine"]["nproc"] and doc["loadavg_before"]
    # Every message of both clients counted, the API's CPU divided by them.
    assert live["clients_closed"] == [] and len(live["messages_per_s_per_client"]) == 2
    assert live["messages_received"] >= 2 * 3 * 3 * 5  # pose, state, tf: 3 robots, 5 s or more
    assert (
        0
        < live["api_cpu_us_per_message"]
        == pytest.approx(1e6 * live["api_cpu_s"] / live["messages_received"], rel=0.01)
    )
    assert "marginal_cpu_us_per_message" in live and live["no_clients_api_cpu_percent"] > 0
    # Each pose published while measured reached both clients, timed from its publish (one
    # clock); those of the last seconds may still be on their way when the clients stop.
    assert live["poses_published_in_window"] >= 3 * 2 and live["poses_received_fraction_min"] == 1
    assert live["pose_latency_samples"] >= 2 * live["poses_published_in_window"]
    assert 0 < live["pose_latency_p50_ms"] <= live["pose_latency_p95_ms"] < 30_000
    # Three timed seeks (and the cold one apart), each frame holding the three robots.
    assert len(seek["seeks"]) == 3 and not seek["reused"] and seek["server_errors"] == []
    assert seek["incomplete"] == 0, seek["seeks"]
    assert seek["first_seek"]["robots"] == 3 and seek["load_s"] > 0
    for s in seek["seeks"]:
        lo, hi = seek["window_ms"]
        assert s["robots"] == 3 and lo <= s["at_ms"] < hi
        assert 0 < s["grid_ms"] <= s["frame_ms"] < 120_000
    assert 0 < seek["frame_p50_ms"] <= seek["frame_p95_ms"]
    assert doc["summary"]["seek_frame_p95_ms"] == seek["frame_p95_ms"]
    # Progress in the terminal and in the run's log.
    log = (data / "bench-foxglove.log").read_text()
    assert "clients connected" in log and "seek 3/3" in log and "summary" in log
    assert "seek 3/3" in done.stderr
