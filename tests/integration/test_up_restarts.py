"""`mapservice up` restarted while a robot publishes at QoS 1 loses nothing it acknowledged:
Ctrl-C (SIGINT), kill -9 of its process group and kill -9 of `up` alone, with `--auth` (the
stricter start: the same restarts, and Mosquitto's own restart to read a robot added
while `up` runs; without `--auth` only the credentials differ, and a run of each cost this
suite two minutes of a worker). The robot is a paho client with a persistent session that counts PUBACKs; the
gateway's persistent session holds what arrives while it is down. Each restart must also
find the ports free (no component outlives its `up`). Bounded: about two minutes a test."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import paho.mqtt.client as mqtt
import pytest

from mapservice.adapters.mqtt_client import PollingClient
from mapservice.core.wire2019 import encode_coordinates, format_timestamp
from mapservice.local import embedded, lifetime
from mapservice.local.embedded import free_port
from tests.fixtures.paths import ROOT
from tests.fixtures.up import Up, children
from tests.integration.test_up_auth import connect_code

pytestmark = [
    pytest.mark.long,
    pytest.mark.integration,
    pytest.mark.skipif(not embedded.mosquitto_installed(), reason="needs mosquitto"),
]

# Each running `up` acknowledges this many poses published after it started (about 2 s of
# the robot's): the faults come under load, and waiting for them rather than for a fixed
# time also proves the robot reconnected.
ACKED_EACH_RUN = 100
# While `up` is down the robot publishes on into its session (about 1 s of poses).
SENT_WHILE_DOWN = 50


def up_on(data_dir, api_port: int, mqtt_port: int, *args: str) -> Up:
    """`mapservice up` without robots or history on given ports (the robot reconnects to
    the same broker address)."""
    return Up(data_dir, "--robots", "0", "--history-days", "0", *args, ports=(api_port, mqtt_port))


class Robot:
    """Publishes a pose every 20 ms at QoS 1 (persistent session, reconnecting); a pose
    counts as acknowledged when its PUBACK arrives."""

    def __init__(self, port: int, robot_id: str, password: str | None = None) -> None:
        self.robot_id = robot_id
        self.client = PollingClient(
            mqtt.CallbackAPIVersion.VERSION2, client_id=robot_id, clean_session=False
        )
        if password:
            self.client.username_pw_set(robot_id, password)
        self.client.reconnect_delay_set(0.2, 1)
        self.client.max_queued_messages_set(0)
        self.client.max_inflight_messages_set(100)
        self.sent: dict[int, int] = {}  # mid -> the pose's timestamp (ms)
        self.acked: set[int] = set()
        self.early: set[int] = set()  # mids whose PUBACK came before publish() returned
        self.lock = threading.Lock()
        self.client.on_publish = self._on_publish
        self.client.connect("127.0.0.1", port, keepalive=5)
        self.client.loop_start()
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _on_publish(self, _c, _u, mid, reason_code, _p) -> None:
        if reason_code.is_failure:
            return
        with self.lock:
            if mid in self.sent:
                self.acked.add(self.sent[mid])
            else:
                self.early.add(mid)

    def _run(self) -> None:
        ts = int(time.time() * 1000)
        while self.running:
            ts = max(ts + 1, int(time.time() * 1000))
            # Never hold our lock while calling paho: its network thread calls _on_publish
            # holding paho's own message lock, and publish() takes that lock too (holding
            # ours across it deadlocked the robot after a reconnect's burst of PUBACKs).
            info = self.client.publish(
                f"iot/coordinates/{self.robot_id}",
                encode_coordinates(self.robot_id, format_timestamp(ts), 1.0, 2.0),
                qos=1,
            )
            with self.lock:  # the PUBACK may have arrived before publish() returned its mid
                self.sent[info.mid] = ts
                if info.mid in self.early:
                    self.early.discard(info.mid)
                    self.acked.add(ts)
            time.sleep(0.02)

    def wait_acked_since(self, since_ms: int, count: int = ACKED_EACH_RUN) -> None:
        """Until `count` poses stamped from `since_ms` on are acknowledged."""
        deadline = time.monotonic() + 90
        while True:
            with self.lock:
                acked = sum(ts >= since_ms for ts in self.acked)
            if acked >= count:
                return
            assert time.monotonic() < deadline, f"{acked} of {count} poses acknowledged"
            time.sleep(0.1)

    def wait_sent(self, count: int = SENT_WHILE_DOWN) -> None:
        """Until `count` more poses are published (queued in the session while disconnected)."""
        with self.lock:
            target = len(self.sent) + count
        deadline = time.monotonic() + 30
        while True:
            with self.lock:
                sent = len(self.sent)
            if sent >= target:
                return
            assert time.monotonic() < deadline, f"the robot stopped publishing ({sent})"
            time.sleep(0.05)

    def stop(self, timeout_s: float = 30) -> None:
        """Stops publishing and waits for the PUBACKs of what is in flight."""
        self.running = False
        self.thread.join()
        deadline = time.monotonic() + timeout_s
        while len(self.acked) < len(self.sent) and time.monotonic() < deadline:
            time.sleep(0.2)
        self.client.disconnect()
        self.client.loop_stop()


def stored_timestamps(up: Up, robot_id: str, from_ms: int) -> list[int]:
    rows = up.api(
        "/api/v1/poses",
        robotId=robot_id,
        limit=100_000,
        **{"from": from_ms, "to": int(time.time() * 1000) + 60_000},
    ).json()
    return [row["ts_ms"] for row in rows]


def restarted(up: Up, how: str, data_dir, robot: Robot, *args: str) -> Up:
    """Ends `up` as `how` says and starts it again on the same ports and data dir; the
    robot publishes on into a broker that is down, and its session queues."""
    if how == "SIGINT":
        up.proc.send_signal(signal.SIGINT)
    elif how == "kill -9 of its process group":
        os.killpg(up.proc.pid, signal.SIGKILL)
    elif how == "kill -9 of up alone":
        up.proc.kill()
    up.proc.wait(60)
    robot.wait_sent()
    return up_on(data_dir, up.api_port, up.mqtt_port, *args)


@pytest.mark.timeout(420)
def test_up_restarted_three_ways_stores_every_acknowledged_pose_once(tmp_path):
    """A robot publishes 50 poses/s while `up --auth` is stopped with Ctrl-C, killed with its
    process group and killed alone, each time started again, and while a robot is added:
    every pose the broker acknowledged is stored, none twice. (Before: `up`'s SIGHUP to the
    restarted Mosquitto lost what was queued for the gateway; after a kill -9 the next `up`
    failed on its own orphans' ports.)"""
    data = tmp_path / "data"
    args = ("--auth",)
    up = up_on(data, free_port(), free_port(), *args)
    robot_id = "controller-1"  # `up --auth` gives the /controller page's robot a credential
    password = json.loads((data / "secrets" / "robots.json").read_text())[robot_id]
    started_ms = int(time.time() * 1000) - 1_000
    robot = Robot(up.mqtt_port, robot_id, password)
    try:
        robot.wait_acked_since(started_ms)
        for how in ("SIGINT", "kill -9 of its process group", "kill -9 of up alone"):
            up = restarted(up, how, data, robot, *args)
            robot.wait_acked_since(int(time.time() * 1000))
        # A robot added while `up` runs: `up` restarts its broker to read the new
        # credential (a SIGHUP here would lose what is queued for the gateway).
        added = subprocess.run(
            [
                sys.executable,
                "-m",
                "mapservice.cli",
                "robot",
                "add",
                "added-while-up-runs",
                "--data-dir",
                str(data),
                "--json",
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert added.returncode == 0, added.stderr
        up.wait_for("Mosquitto restarted to read them", 20)
        new_password = json.loads(added.stdout)["password"]
        assert connect_code(up.mqtt_port, "added-while-up-runs", new_password) == 0
        robot.wait_acked_since(int(time.time() * 1000))
        robot.stop()
        acked = set(robot.acked)
        deadline = time.monotonic() + 60
        stored = stored_timestamps(up, robot_id, started_ms)
        while not acked <= set(stored) and time.monotonic() < deadline:
            time.sleep(1)
            stored = stored_timestamps(up, robot_id, started_ms)
        time.sleep(2)  # a duplicate would show up now
        stored = stored_timestamps(up, robot_id, started_ms)
        lost = acked - set(stored)
        twice = len(stored) - len(set(stored))
        print(
            f"\n--auth: published {len(robot.sent)}, "
            f"acknowledged {len(acked)}, stored {len(set(stored))}, lost {len(lost)}, "
            f"stored twice {twice}"
        )
        assert len(acked) > 500
        assert not lost, f"{len(lost)} of {len(acked)} acknowledged poses lost"
        assert twice == 0
    finally:
        robot.running = False
        up.stop()


@pytest.mark.timeout(240)
def test_up_ends_a_component_that_outlived_a_killed_up(tmp_path):
    """The guard that stops the components when `up` dies is killed, the API stopped
    (SIGSTOP) and `up` killed with kill -9: the API still holds its port. The next `up`
    finds it in the pid file, says so, ends it and comes up on the same ports."""
    data = tmp_path / "data"
    up = up_on(data, free_port(), free_port())
    server = children(up.proc.pid)["api"]
    try:
        guard = json.loads((data / "up.pids.json").read_text())["components"]
        os.kill(next(c["pid"] for c in guard if c["name"] == "guard"), signal.SIGKILL)
        os.kill(server, signal.SIGSTOP)
        up.proc.kill()
        up.proc.wait(30)
        time.sleep(1)
        assert lifetime.start_time(server) is not None, "the stopped API did not outlive up"
        up = up_on(data, up.api_port, up.mqtt_port)
        assert "ended without stopping its components" in up.output
        assert f"api (pid {server})" in up.output
        assert lifetime.start_time(server) is None
        assert up.api("/readyz").status_code == 200
    finally:
        up.stop()
        if lifetime.start_time(server) is not None:  # not ended: do not leave it behind
            os.kill(server, signal.SIGKILL)
