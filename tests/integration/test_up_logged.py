"""`mapservice up` with its output to a pipe (a log file, a CI job): its first run says how
far it got, its address table is whole, and nothing it writes is readable by other users."""

from __future__ import annotations

import json
import os
import stat

import pytest

from tests.fixtures.up import Up

pytestmark = pytest.mark.integration


def piped_up(data_dir, *args: str) -> Up:
    """`up` whose stdout and stderr are a pipe, with no COLUMNS to widen its console."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    return Up(data_dir, *args, env=env, ready_within_s=200)


@pytest.mark.timeout(300)
def test_a_logged_first_run_shows_progress_a_whole_table_and_keeps_its_files_private(tmp_path):
    """To a pipe: the demo history logs its progress, each start-up step logs a line, the
    table's long values (the analyst password's path, deep in a long data dir) are whole;
    the data dir is 0700 and no file or directory in it is open to group or others, also
    what was there before (a file 0644 from an older release)."""
    data = tmp_path / ("a-data-dir-with-a-long-name-" * 3) / "data"
    data.mkdir(parents=True)
    old = data / "left-by-an-older-release.txt"
    old.write_text("x")
    old.chmod(0o644)
    data.chmod(0o755)
    up = piped_up(data, "--auth", "--robots", "1", "--history-days", "0.3")
    try:
        out = up.output
        assert "simulating the last 0.3 days of 1 robots" in out and "done_percent=" in out
        for step in (
            "starting Kafka (Apache Kafka",
            "the MQTT broker and the ClickHouse server",
            "starting the processors (creating the ClickHouse schema), the API and the "
            "MQTT-to-Kafka gateway",
        ):
            assert step in out
        password_path = str(data / "secrets" / "analyst-password")
        assert any(password_path in line for line in out.splitlines()), out[-3000:]
        assert "…" not in out.split("mapservice is up", 1)[1]
        assert stat.S_IMODE(data.stat().st_mode) == 0o700
        exposed = []
        for root, dirs, files in os.walk(data):
            for name in dirs + files:
                path = os.path.join(root, name)
                try:
                    mode = os.lstat(path).st_mode
                except FileNotFoundError:  # a running engine's scratch file, gone meanwhile
                    continue
                if not stat.S_ISLNK(mode) and mode & 0o077:
                    exposed.append(f"{oct(stat.S_IMODE(mode))} {os.path.relpath(path, data)}")
        assert not exposed, exposed
        for must in (
            "secrets/robots.json",
            "logs/processors.log",
            "logs/api.log",
            "logs/clickhouse.log",
            "secrets/clickhouse-password",
            "logs/mosquitto.log",
            "mqtt/passwd",
            "mqtt/acl",
        ):
            assert (data / must).exists(), must
        # The API in a process of its own, apart from the history consumer's; the ClickHouse
        # server the one process that opens the chDB directory (no `serve`).
        recorded = {
            c["name"]: c for c in json.loads((data / "up.pids.json").read_text())["components"]
        }
        assert {"clickhouse", "processors", "api"} <= set(recorded) and "server" not in recorded
        assert recorded["api"]["command"][-1] == "api"
        processors = recorded["processors"]["command"]
        assert processors[processors.index("mapservice.cli") + 1] == "processors"
        # Still told whether the history is stored (the processors' own truth).
        assert up.api("/readyz").json()["checks"]["history_store"] is True
        assert up.api("/api/v1/status").json()["history"]["storing"] is True
    finally:
        up.stop()
