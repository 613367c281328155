"""`mapservice bench sink` drains what it published through the history consumer."""

from __future__ import annotations

import json
import subprocess
import sys

from mapservice.local import kafka_broker


def test_one_sink_run_counts_every_published_event() -> None:
    """A small run stores all of its events in the counting store and reports their CPU cost."""
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "bench",
            "sink",
            "--one",
            "batch",
            "--events",
            "25000",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line is not None, out.stdout[-2000:] + out.stderr[-2000:]
    result = json.loads(line[7:])
    assert result["complete"] and 0 < result["events"] <= 25_000 and result["cpu_us_per_event"] > 0
    # The broker `up` runs: Apache Kafka wherever Java is, tansu only as the fallback.
    assert result["broker"] == ("apache" if kafka_broker.java_binary() else "tansu"), result
