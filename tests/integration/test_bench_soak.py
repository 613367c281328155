"""`mapservice bench soak` end to end on a tiny fleet for 21 seconds: it samples every
component, stores what the robots publish, and says a short run is not representative."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Beside other modules' stacks in the parallel step: a tiny fleet, judged by what was sampled
# and stored; its one time bound (freshness under the 5 s sampling period) holds under load.


@pytest.mark.timeout(300)
def test_a_short_soak_samples_every_component_and_says_it_is_not_representative(tmp_path) -> None:
    """Three robots for 21 s, sampled every 5 s (five samples): memory and CPU per
    component, events stored, no dead letters, a freshness under the sampling period, and
    the short-run warning."""
    out = tmp_path / "soak.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "bench",
            "soak",
            "--minutes",
            "0.35",
            "--robots",
            "3",
            "--sample-s",
            "5",
            "--data-dir",
            str(tmp_path / "data"),
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=280,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert "not representative" in done.stdout
    result = json.loads(out.read_text())
    samples, summary = result["samples"], result["summary"]
    assert len(samples) >= 4
    assert {"kafka", "mqtt", "server", "gateway"} <= set(samples[-1]["rss_mb"])
    assert all(rss > 1 for rss in samples[-1]["rss_mb"].values())
    # Anonymous memory, on which growth is judged, is part of the resident size.
    assert all(
        0 < samples[-1]["anon_mb"][n] <= samples[-1]["rss_mb"][n] for n in samples[-1]["rss_mb"]
    )
    assert summary["stored_events"] > 3 * 10 and summary["dead_letters"] == 0
    assert summary["freshness_median_s"] is not None and summary["freshness_median_s"] < 5
    assert summary["representative"] is False
    # The embedded Apache Kafka's log on disk is sampled beside the components' memory.
    if result["kafka"] == "apache":
        assert samples[-1]["disk_mb"]["kafka_log"] > 0
        assert result["kafka_broker"]["heap_mb"] >= 128
    # serve's memory split: ClickHouse's tracker (chDB lives in serve) and Python's allocator.
    inside = samples[-1]["serve_inside"]
    assert inside["chdb_mb"] > 0 and inside["python_blocks_k"] > 10
    assert summary["serve_inside"]["chdb_mb"]["last"] == inside["chdb_mb"]
