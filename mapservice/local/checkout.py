"""Paths inside a source checkout that local tooling uses: the repository and the built UI
(the demo map is `mapservice.robot.DEFAULT_MAP`).

A pip-installed service has neither (it is given a map and serves the UI its image holds),
so only `mapservice up`, the simulators and the benchmarks look here.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
UI_INDEX = ROOT / "replay-ui" / "dist" / "index.html"
