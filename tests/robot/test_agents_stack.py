"""Two robot agents (`mapservice robot`) share one real service (Apache Kafka, Mosquitto, chDB,
processors, API): A uploads its map, B downloads it, A's map edit reaches B's map file."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from mapservice.adapters.ros_map import load_ros_map, write_pgm
from mapservice.local import embedded
from mapservice.local.stack import Stack
from tests.fixtures.paths import MAPS, ROOT

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def empty_stack(tmp_path_factory):
    """A service with no map meta yet (the first robot brings it), advertising chunkUrls
    that resolve on this API."""
    api_port = embedded.free_port()
    stack = Stack(
        tmp_path_factory.mktemp("robot-stack"),
        mqtt="mosquitto",
        api_port=api_port,
        extra_env={"MAPSERVICE_PUBLIC_BASE_URL": f"http://127.0.0.1:{api_port}"},
    )
    with stack.running():
        yield stack


def robot_dir(tmp_path, name):
    d = tmp_path / name
    d.mkdir()
    for suffix in ("yaml", "pgm"):
        shutil.copy(MAPS / f"depot.{suffix}", d / f"depot.{suffix}")
    return d / "depot.yaml"


def start_robot(stack, yaml_path, robot_id, log_path) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "robot",
            "--map",
            str(yaml_path),
            "--robot-id",
            robot_id,
            "--api",
            stack.api_url,
            "--mqtt",
            stack.mqtt_url,
            "--period",
            "0.5",
        ],
        cwd=ROOT,
        env=stack.env(),
        stdout=open(log_path, "wb"),
        stderr=subprocess.STDOUT,
    )


def wait_until(pred, what, timeout_s=90.0, logs=()):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.3)
    raise AssertionError(
        f"timed out waiting for {what}\n"
        + "\n".join(p.read_text()[-3000:] for p in logs if p.exists())
    )


def pixels(yaml_path):
    try:
        return load_ros_map(yaml_path).pixels
    except (OSError, ValueError):
        return None


def test_robot_b_converges_to_robot_a(empty_stack, tmp_path) -> None:
    """A finds no meta and uploads meta + 28 chunks; B (with a different local map) finds
    them and downloads the map; a pallet A draws into its PGM arrives in B's PGM."""
    stack = empty_stack
    a_yaml, b_yaml = robot_dir(tmp_path, "a"), robot_dir(tmp_path, "b")
    original = load_ros_map(a_yaml)
    stale = original.pixels.copy()
    stale[200:260, 400:460] = 0  # B's map is out of date
    write_pgm(b_yaml.with_suffix(".pgm"), stale)
    logs = [tmp_path / "a.log", tmp_path / "b.log"]
    a = start_robot(stack, a_yaml, "robot-a", logs[0])
    b = None
    try:

        def stored_chunks():
            resp = httpx.get(
                f"{stack.api_url}/api/chunk-service/chunks",
                params={"latest": "true", "limit": 100, "reduced": "true"},
                timeout=10,
            )
            return resp.json() if resp.status_code == 200 else []

        def stored_meta():
            resp = httpx.get(f"{stack.api_url}/api/chunk-service/meta", timeout=10)
            return resp.json() if resp.status_code == 200 else None

        wait_until(
            lambda: len(stored_chunks()) == 28, "robot A's 28 chunks to be stored", logs=logs
        )
        assert {c["robotId"] for c in stored_chunks()} == {"robot-a"}
        # Meta and chunks travel on different topics: B must not start before the meta is
        # stored, or it would find none and upload its own map (as a 2019 robot would).
        wait_until(lambda: stored_meta() is not None, "robot A's meta to be stored", logs=logs)
        meta = stored_meta()
        assert (meta["width"], meta["CHUNK_ROWS"], meta["resolution"]) == (604, 4, 0.05)

        b = start_robot(stack, b_yaml, "robot-b", logs[1])
        wait_until(lambda: "downloaded map" in logs[1].read_text(), "robot B's download", logs=logs)
        wait_until(
            lambda: np.array_equal(pixels(b_yaml), original.pixels),
            "B's map to equal the service's",
            logs=logs,
        )

        edited = original.pixels.copy()
        edited[150:190, 250:290] = 0  # a pallet in chunk (1, 2)
        write_pgm(a_yaml.with_suffix(".pgm"), edited)
        wait_until(
            lambda: np.array_equal(pixels(b_yaml), edited),
            "A's pallet to reach B's map file",
            logs=logs,
        )
        # B writes its map file first and logs the integration after it: wait for the line.
        wait_until(
            lambda: "integrated chunks of other robots" in logs[1].read_text(),
            "B to log the integration",
            logs=logs,
        )
        a_log, b_log = logs[0].read_text(), logs[1].read_text()
        assert "published local changes" in a_log, a_log
        assert "chunkUrl unreadable" not in b_log, b_log  # fetched through chunkUrl
    finally:
        for proc in (a, b):
            if proc is not None:
                proc.send_signal(signal.SIGTERM)
        for proc, log in zip((a, b), logs):
            if proc is not None:
                assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]
