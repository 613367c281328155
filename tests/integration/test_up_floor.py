"""`mapservice up` end to end: the real floor from the start, nav2's small maps, and a
supervisor that restarts a killed component (each test runs one `up`, bounded to ~2 min)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from mapservice.adapters.ros_map import load_ros_map, slice_chunks
from mapservice.core.wire2019 import content_hash, encode_coordinates, format_timestamp
from mapservice.robot.map_upload import MARKER, UPLOADER_ID
from tests.fixtures.paths import MAPS
from tests.fixtures.up import Up, children

pytestmark = [pytest.mark.integration, pytest.mark.long]


def test_fresh_up_serves_the_map_file_chunk_by_chunk(tmp_path):
    """On a fresh data dir, demo history is written first; the map at now equals the sliced
    map file within a minute of ready, except chunks a simulated robot changed; a second
    `up` neither writes history nor uploads again."""
    warehouse = load_ros_map(MAPS / "warehouse.yaml")
    expected = {key: content_hash(px).hex() for key, px in slice_chunks(warehouse).items()}
    up = Up(tmp_path / "data", "--robots", "2", "--history-days", "0.05")
    try:
        assert "wrote 0.05 days of demo history" in up.output
        history = up.api("/api/v1/stats").json()["poses"]
        assert history >= 2 * 0.05 * 86_400 / 3 * 0.9, (
            history
        )  # poses every 3 s, before the live ones
        deadline, chunks = time.monotonic() + 60, []
        while time.monotonic() < deadline:
            chunks = up.api("/api/v1/map").json()["chunks"]
            if len(chunks) == len(expected):
                break
            time.sleep(1)
        assert len(chunks) == len(expected), f"{len(chunks)} of {len(expected)} chunks at now"
        changed = 0
        for c in chunks:
            if c["robotId"] == UPLOADER_ID:
                assert c["content_hash"] == expected[(c["row"], c["column"])], c
            else:
                assert c["robotId"].startswith("sim-"), c
                changed += 1
        assert changed <= 12, f"{changed} chunks differ from the map file"
    finally:
        up.stop()
    assert (tmp_path / "data" / MARKER).exists()
    again = Up(tmp_path / "data", "--robots", "0")
    try:
        assert "as stored" in again.output and "chunks published" not in again.output
        assert "demo history" not in again.output
    finally:
        again.stop()


def test_up_on_tb3_sandbox_runs_and_restarts_a_killed_gateway(tmp_path):
    """`up --map tb3_sandbox` runs 5 simulated robots for a minute with no component
    exiting; a SIGKILLed gateway is restarted, said on the console, and poses flow again."""
    up = Up(
        tmp_path / "data",
        "--map",
        str(MAPS / "tb3_sandbox.yaml"),
        "--robots",
        "5",
        "--restart-base-s",
        "0.5",
        "--history-days",
        "0",
    )
    try:
        assert "demo history" not in up.output
        time.sleep(60)
        assert "exited" not in up.output, up.output[-4000:]
        robots = up.api("/api/v1/robots").json()["robots"]
        assert len([r for r in robots if r["robotId"].startswith("sim-") and r["online"]]) == 5, (
            robots
        )

        os.kill(children(up.proc.pid)["gateway"], signal.SIGKILL)
        up.wait_for("gateway exited", 10)
        up.wait_for("gateway restarted", 60)

        import paho.mqtt.publish as publish

        now = int(time.time() * 1000)
        publish.single(
            "iot/coordinates/after-restart",
            encode_coordinates("after-restart", format_timestamp(now), 1.0, 2.0, (0, 0, 0, 1)),
            qos=1,
            hostname="127.0.0.1",
            port=up.mqtt_port,
        )
        deadline, found = time.monotonic() + 20, []
        while time.monotonic() < deadline and not found:
            found = up.api(
                "/api/v1/poses",
                robotId="after-restart",
                **{"from": format_timestamp(now - 60_000), "to": format_timestamp(now + 60_000)},
            ).json()
            time.sleep(0.5)
        assert found, "no pose stored after the gateway restarted"
    finally:
        up.stop()
