"""`mapservice bench incidents`: a short run reports the detection's CPU per pose, counts
only the poses after the warm-up, and finds incidents (the fleet makes them)."""

from __future__ import annotations

import json
import subprocess
import sys

from mapservice.bench.incidents import run


def test_a_short_run_counts_the_poses_after_the_warm_up_and_finds_incidents() -> None:
    result = run(robots=30, seconds=40, warm_s=10, floor_m2=20.0)
    assert result["poses"] == 30 * 30
    assert result["us_per_pose"] > 0
    assert result["findings"] > 0


def test_the_command_writes_its_figures(tmp_path) -> None:
    out = tmp_path / "incidents.json"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "bench",
            "incidents",
            "--robots",
            "10",
            "--seconds",
            "6",
            "--warm-s",
            "2",
            "--rounds",
            "1",
            "--json",
            str(out),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    figures = json.loads(out.read_text())
    assert figures["runs"]["10"]["median_us_per_pose"] > 0
    assert figures["yardstick_ms"] > 0 and figures["machine"]
