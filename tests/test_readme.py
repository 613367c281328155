"""The README runs: its try-it block works against `mapservice up` (which also stops cleanly
and resumes on the same data). The reference pages it links are checked by test_docs.py."""

from __future__ import annotations

import json
import os
import subprocess
import time

import httpx
import pytest

from mapservice.local.embedded import ensure_port_free
from tests.fixtures.paths import README
from tests.fixtures.up import Up

pytestmark = pytest.mark.long


def try_it_block() -> str:
    text = README.read_text()
    block = text.split("<!-- try-it -->", 1)[1].split("<!-- /try-it -->", 1)[0]
    return block.split("```bash", 1)[1].rsplit("```", 1)[0]


def start_up(data_dir, ports: tuple[int, int] | None = None) -> Up:
    # A fresh data dir first gets its week of demo history.
    return Up(data_dir, "--robots", "2", ports=ports, env=dict(os.environ), ready_within_s=240)


def stop_up(up: Up) -> int | None:
    up.stop()
    return up.proc.returncode


@pytest.mark.integration
def test_try_it_block_against_mapservice_up(tmp_path):
    """`mapservice up` comes up; the README's mosquitto_pub pose is queryable within 2 s; Ctrl-C
    stops everything; a second `up` on the same data dir still has it."""
    data_dir = tmp_path / "data"
    up = start_up(data_dir)
    api_port, mqtt_port = up.api_port, up.mqtt_port
    try:
        script = (
            try_it_block()
            .replace("-p 1883", f"-p {mqtt_port}")
            .replace("127.0.0.1:8080", f"127.0.0.1:{api_port}")
        )
        publish, rest = script.split("sleep 1", 1)
        started = time.monotonic()
        subprocess.run(["bash", "-euc", publish], check=True, timeout=30)
        found = []
        while time.monotonic() - started < 2.0 and not found:
            found = json.loads(
                subprocess.run(
                    ["bash", "-euc", rest], check=True, timeout=30, capture_output=True, text=True
                ).stdout
            )
        assert found, "the README's pose was not queryable within 2 s"
        assert found[0]["robotId"] == "demo-robot"
        assert found[0]["position"] == [10.0, 20.0, 0.0]
        assert found[0]["loaded"] is True and found[0]["charging"] is False
        deadline = time.monotonic() + 60
        while httpx.get(f"http://127.0.0.1:{api_port}/api/v1/stats").json()["poses"] < 5:
            assert time.monotonic() < deadline, "the simulated robots never published"
            time.sleep(0.5)
    finally:
        code = stop_up(up)
    assert code == 0
    for port in (api_port, mqtt_port):
        ensure_port_free(port, "a component `up` should have stopped")

    up = start_up(data_dir, (api_port, mqtt_port))
    try:
        now = time.time_ns() // 1_000_000
        rows = httpx.get(
            f"http://127.0.0.1:{api_port}/api/v1/poses",
            params={"robotId": "demo-robot", "from": now - 3_600_000, "to": now},
        ).json()
        assert len(rows) == 1
    finally:
        assert stop_up(up) == 0
