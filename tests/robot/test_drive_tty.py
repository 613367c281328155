"""The interactive robot driven through a real terminal (tmux) against a real Mosquitto:
arrow keys move it (poses go out), 'b' paints the chunk under it black (a chunk goes out)."""

from __future__ import annotations

import base64
import os
import shlex
import shutil
import subprocess
import sys
import threading
import time
import zlib

import msgspec
import pytest

from mapservice.adapters.mqtt_client import make_client
from tests.fixtures.paths import MAPS, ROOT

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(shutil.which("tmux") is None, reason="needs tmux (apt-get install tmux)"),
]


class Tmux:
    """A real terminal: a detached tmux session on its own server socket."""

    def __init__(self, name: str, command: list[str], env: dict[str, str]) -> None:
        self.base = ["tmux", "-L", name]
        self.name = name
        exports = " ".join(f"{k}={shlex.quote(v)}" for k, v in env.items())
        subprocess.run(
            [
                *self.base,
                "new-session",
                "-d",
                "-s",
                name,
                "-x",
                "100",
                "-y",
                "30",
                f"env {exports} {shlex.join(command)}; echo EXITED=$?; sleep 30",
            ],
            check=True,
            timeout=10,
        )

    def keys(self, *keys: str) -> None:
        subprocess.run([*self.base, "send-keys", "-t", self.name, *keys], check=True, timeout=10)

    def screen(self) -> str:
        return subprocess.run(
            [*self.base, "capture-pane", "-p", "-t", self.name],
            check=True,
            timeout=10,
            capture_output=True,
            text=True,
        ).stdout

    def wait_screen(self, text: str, timeout_s: float = 30.0) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            screen = self.screen()
            if text in screen:
                return screen
            time.sleep(0.2)
        raise AssertionError(f"{text!r} never appeared on the screen:\n{self.screen()}")

    def kill(self) -> None:
        subprocess.run([*self.base, "kill-server"], timeout=10, capture_output=True)


def subscribe(port: int):
    received: list[tuple[str, dict]] = []
    ready = threading.Event()
    client = make_client(f"tui-test-{os.getpid()}")
    client.on_connect = lambda c, *_: (c.subscribe("iot/#", qos=1), ready.set())
    client.on_message = lambda c, u, m: received.append((m.topic, msgspec.json.decode(m.payload)))
    client.connect("127.0.0.1", port)
    client.loop_start()
    assert ready.wait(10)
    time.sleep(0.3)
    return client, received


def wait_for(pred, timeout_s=15.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.1)
    return False


def test_drive_and_paint_through_a_terminal(mosquitto) -> None:
    """Two presses of Right move the robot 2 x 10 px = 1.0 m east (screen and poses say so);
    'b' publishes the chunk under the robot, all black; q quits cleanly."""
    client, received = subscribe(mosquitto)
    env = {"TERM": "xterm", "PYTHONPATH": str(ROOT), "PATH": os.environ.get("PATH", "")}
    term = Tmux(
        f"mapservice-drive-{os.getpid()}",
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "drive",
            "--map",
            str(MAPS / "depot.yaml"),
            "--mqtt",
            f"mqtt://127.0.0.1:{mosquitto}",
            "--robot-id",
            "tui-1",
            "--start",
            "15.1",
            "7.6",
            "--no-size-check",
        ],
        env,
    )
    try:
        screen = term.wait_screen("chunk (1, 3)")
        assert "x=15.12 y=7.62 m" in screen and "@" in screen
        poses = lambda: [d for t, d in received if t == "iot/coordinates/tui-1"]  # noqa: E731
        assert wait_for(lambda: len(poses()) >= 1), "no heartbeat pose"
        start = poses()[-1]["pose"]["position"]
        assert (start["x"], start["y"]) == (15.125, 7.625)
        term.keys("Right")
        term.keys("Right")
        term.wait_screen("x=16.12 y=7.62 m")
        assert wait_for(lambda: any(p["pose"]["position"]["x"] == 16.125 for p in poses()))
        term.keys("b")
        term.wait_screen("painted chunk (1, 3) black")
        chunks = lambda: [d for t, d in received if t == "iot/chunks/create"]  # noqa: E731
        assert wait_for(lambda: len(chunks()) == 1), "the painted chunk was not published"
        chunk = chunks()[0]
        assert (chunk["row"], chunk["column"], chunk["robotId"]) == (1, 3, "tui-1")
        assert zlib.decompress(base64.b64decode(chunk["pgmB64compressedData"])) == bytes(10_000)
        term.keys("q")
        term.wait_screen("EXITED=0")
    finally:
        term.kill()
        client.loop_stop()
        client.disconnect()
