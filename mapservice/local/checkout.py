"""Paths inside a source checkout that local tooling uses: the repository and the UI's test
build (the demo map is `mapservice.robot.DEFAULT_MAP`).

A pip-installed service has neither (it is given a map and serves the UI its image holds),
so only `mapservice up`, the simulators, the benchmarks and the tests look here.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# The replay page built with window.__replay (replay-ui/src/lib/testhook.ts), which the
# browser tests and `mapservice bench ui` drive; `make ui` builds it beside dist/, the
# production page without the hook that `mapservice up` serves.
TEST_UI_DIR = ROOT / "replay-ui" / "dist-test"
# The environment that has an API (a stack's, an `up`'s, a lone `mapservice api`) serve it.
TEST_UI_ENV = {"MAPSERVICE_UI_DIR": str(TEST_UI_DIR)}
# Foxglove's own npm WebSocket client: the integration test's (client.mjs) and
# `mapservice bench foxglove`'s (bench.mjs), one package.json for both.
FOXGLOVE_CLIENT_DIR = ROOT / "tests" / "foxglove_client"
