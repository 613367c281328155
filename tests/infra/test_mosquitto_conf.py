"""The shipped Mosquitto config (infra/mosquitto/mosquitto.conf): the tuning the gateway
relies on, the store saved as often as the embedded broker's, and a local mosquitto
starting with it (when one is installed)."""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from tests.infra.manifests import MOSQUITTO_CONF, compose, compose_env


def test_mosquitto_conf_has_the_tuning_the_gateway_relies_on():
    """mosquitto.conf sets nodelay, 1000 in flight, a large queue, persistence and a
    WebSocket listener for browsers; compose mounts it and tells the API where it is."""
    options: dict[str, str] = {}
    listeners: list[str] = []
    for line in MOSQUITTO_CONF.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.strip().partition(" ")
            options[key] = value.strip()
            if key == "listener":
                listeners.append(value.strip())
            elif key == "protocol":
                listeners[-1] += f" {value.strip()}"
    assert listeners == ["1883", "9001 websockets"]
    assert options["set_tcp_nodelay"] == "true"
    assert int(options["max_inflight_messages"]) == 1000
    assert int(options["max_queued_messages"]) >= 100_000
    assert options["persistence"] == "true"
    services = compose()["services"]
    assert "/mosquitto/data" in " ".join(services["mosquitto"]["volumes"])
    assert (
        "./mosquitto/mosquitto.conf:/mosquitto/config/mosquitto.conf:ro"
        in services["mosquitto"]["volumes"]
    )
    # The /controller page reaches the WebSocket listener through the published port.
    assert "9001:9001" in services["mosquitto"]["ports"]
    assert services["api"]["environment"]["MAPSERVICE_MQTT_WS_URL"] == "ws://localhost:9001"
    assert compose_env(services["gateway"])["MAPSERVICE_MQTT_URL"] == "mqtt://mosquitto:1883"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_shipped_mosquitto_saves_its_store_as_often_as_the_embedded_one():
    """infra's Mosquitto persists sessions and queued messages and saves them every second, as the fault-tested embedded broker does."""
    from mapservice.local.embedded import MOSQUITTO_STORE

    lines = MOSQUITTO_CONF.read_text().splitlines()
    assert "persistence true" in lines
    (shipped,) = [line for line in lines if line.startswith("autosave_interval")]
    assert shipped in MOSQUITTO_STORE.splitlines() and shipped == "autosave_interval 1"


def test_mosquitto_starts_with_the_config():
    """The local mosquitto starts with infra/mosquitto/mosquitto.conf (port and data path changed only)."""
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not Path(binary).exists():
        pytest.skip("mosquitto is not installed (make test installs it)")
    with tempfile.TemporaryDirectory(prefix="mapservice-mosquitto-") as tmp:
        # As root, mosquitto drops to its own user: let it write its data here.
        Path(tmp).chmod(0o777)
        run_mosquitto(binary, Path(tmp))


def run_mosquitto(binary: str, tmp_path: Path) -> None:
    port = free_port()
    text, n_listener = re.subn(
        r"(?m)^listener 1883$", f"listener {port} 127.0.0.1", MOSQUITTO_CONF.read_text()
    )
    ws_port = free_port()
    text = re.sub(r"(?m)^listener 9001$", f"listener {ws_port} 127.0.0.1", text)
    text, n_data = re.subn(
        r"(?m)^persistence_location .*$", f"persistence_location {tmp_path}/", text
    )
    assert n_listener == 1 and n_data == 1
    conf = tmp_path / "mosquitto.conf"
    conf.write_text(text)
    proc = subprocess.Popen(
        [binary, "-c", str(conf)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                pytest.fail(f"mosquitto refused the config: {proc.stdout.read()}")
            try:
                for p in (port, ws_port):
                    socket.create_connection(("127.0.0.1", p), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.1)
        else:
            pytest.fail("mosquitto did not listen within 10 s")
    finally:
        proc.terminate()
        proc.wait(10)
