"""Each process imports only what it runs: the API alone never loads the processors (so it
registers and exports none of their metrics)."""

from __future__ import annotations

import subprocess
import sys

from tests.fixtures.paths import ROOT


def test_the_api_process_does_not_import_the_processors() -> None:
    """What `mapservice api` imports up to serving holds no mapservice.processors module."""
    code = """
import sys
from mapservice import cli
cli.build_parser()
import mapservice.server, mapservice.api.app, mapservice.sql.apps
print(sorted(m for m in sys.modules if m.startswith('mapservice.processors')))
"""
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"
