"""The robot tools with per-robot credentials: credentials files, chunk topics, one connection
per robot against a Mosquitto that checks identities."""

from __future__ import annotations

import argparse
import stat
import threading
import time

import pytest

from mapservice.adapters.mqtt_auth import BrokerFiles
from mapservice.adapters.mqtt_client import make_client
from mapservice.adapters.ros_map import load_ros_map
from mapservice.local import embedded
from mapservice.robot.connection import (
    RobotClients,
    RobotMqtt,
    add_mqtt_arguments,
    load_credentials,
    robot_mqtt_from_args,
    save_credential,
)
from mapservice.robot.faults import to_messages
from mapservice.robot.sim import ChunkOut, new_state, step
from tests.fixtures.paths import MAPS


def test_credentials_file_roundtrip(tmp_path):
    """save_credential merges one robot into a 0600 JSON file that load_credentials reads."""
    path = tmp_path / "robots.json"
    save_credential(path, "r1", "p1")
    save_credential(path, "r2", "p2")
    save_credential(path, "r1", "p1b")
    assert load_credentials(path) == {"r1": "p1b", "r2": "p2"}
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    (tmp_path / "bad.json").write_text('["not", "a", "map"]')
    with pytest.raises(ValueError, match="robotId -> password"):
        load_credentials(tmp_path / "bad.json")


def test_chunk_topic_follows_identity_and_flag():
    """Anonymous robots use the 2019 chunk topic, robots with credentials their own; the flag
    overrides either way."""
    assert RobotMqtt("mqtt://h").chunk_topic("r1") == "iot/chunks/create"
    assert RobotMqtt("mqtt://h", {"r1": "p"}).chunk_topic("r1") == "iot/chunks/create/r1"
    assert (
        RobotMqtt("mqtt://h", {"r1": "p"}, per_robot_chunk_topic=False).chunk_topic("r1")
        == "iot/chunks/create"
    )
    assert (
        RobotMqtt("mqtt://h", per_robot_chunk_topic=True).chunk_topic("r1")
        == "iot/chunks/create/r1"
    )
    with pytest.raises(ValueError, match="r2"):
        RobotMqtt("mqtt://h", {"r1": "p"}).check(["r1", "r2"])


def test_flags_build_the_connection(tmp_path):
    """--credentials, --chunk-topic and the TLS flags become a RobotMqtt; the service's CA file
    is the default only for an mqtts:// URL."""
    parser = argparse.ArgumentParser()
    add_mqtt_arguments(parser, many=True)
    save_credential(tmp_path / "c.json", "r1", "p")
    args = parser.parse_args(["--credentials", str(tmp_path / "c.json"), "--chunk-topic", "legacy"])
    conn = robot_mqtt_from_args(args, "mqtts://h:8883", default_ca_file="/ca.pem")
    assert conn.credentials == {"r1": "p"} and conn.chunk_topic("r1") == "iot/chunks/create"
    assert str(conn.tls.ca_file) == "/ca.pem"
    assert (
        robot_mqtt_from_args(parser.parse_args([]), "mqtt://h", default_ca_file="/ca.pem").tls
        is None
    )


def test_sim_messages_carry_their_robot_and_its_chunk_topic():
    """Each simulated message names the robot that sends it; chunks go to the topic the
    connection picks for that robot."""
    state = new_state(load_ros_map(MAPS / "depot.yaml"), 3, seed=1, t_ms=1_700_000_000_000)
    state, out = step(state)
    robot = state.robots[0].robot_id
    out.chunks.append(ChunkOut(robot, 1_700_000_000_000, 0, 0, bytes(10_000)))
    conn = RobotMqtt("mqtt://h", {r.robot_id: "p" for r in state.robots})
    messages, _ = to_messages(out, chunk_topic=conn.chunk_topic)
    assert all(m.robot_id and m.topic.endswith(m.robot_id) for m in messages)
    (chunk,) = [m for m in messages if m.kind == "chunk"]
    assert chunk.topic == f"iot/chunks/create/{robot}"
    legacy, _ = to_messages(out)
    assert [m.topic for m in legacy if m.kind == "chunk"] == ["iot/chunks/create"]


@pytest.fixture
def auth_broker(tmp_path):
    """Mosquitto with identities on a free port: (url, the robots' passwords); the gateway's
    service user has the password "gw"."""
    files = BrokerFiles.in_data_dir(tmp_path)
    files.set_service_user("mapservice-gateway", "gw")
    passwords = {r: files.add_robot(r).password for r in ("r1", "r2")}
    port = embedded.free_port()
    proc = embedded.start_mosquitto(
        port,
        tmp_path / "mosquitto",
        options=embedded.MosquittoOptions(files.password_file, files.acl_file),
    )
    yield f"mqtt://127.0.0.1:{port}", passwords
    embedded.stop(proc)


def test_each_robot_connects_as_itself(auth_broker):
    """RobotClients opens one connection per robot with its own credential; what each publishes
    on its own topics arrives; a wrong password fails at connect with a clear error."""
    url, passwords = auth_broker
    port = int(url.rsplit(":", 1)[1])
    received: list[str] = []
    reader = make_client("reader", username="mapservice-gateway", password="gw")
    subscribed = threading.Event()
    reader.on_subscribe = lambda *_: subscribed.set()
    reader.on_message = lambda _c, _u, m: received.append(m.topic)
    reader.connect("127.0.0.1", port)
    reader.loop_start()
    reader.subscribe([("iot/coordinates/#", 1), ("iot/chunks/create/#", 1)])
    assert subscribed.wait(5)
    clients = RobotClients(RobotMqtt(url, passwords), ["r1", "r2"], "test")
    try:
        clients.connect()
        assert set(clients.clients) == {"r1", "r2"}
        for robot in ("r1", "r2"):
            clients.publish(robot, f"iot/coordinates/{robot}", b"{}").wait_for_publish(5)
            clients.publish(robot, clients.chunk_topic(robot), b"{}").wait_for_publish(5)
        deadline = time.monotonic() + 5
        while len(received) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sorted(received) == [
            "iot/chunks/create/r1",
            "iot/chunks/create/r2",
            "iot/coordinates/r1",
            "iot/coordinates/r2",
        ]
    finally:
        clients.close()
        reader.loop_stop()
    with pytest.raises(PermissionError, match="refused r1's credential"):
        RobotClients(RobotMqtt(url, {"r1": "wrong"}), ["r1"], "test").connect()


def test_a_fleet_without_a_connection_subscribes_nowhere():
    """Where robots have credentials and there is no robot, there is no connection to read
    on, and none is opened for it."""
    clients = RobotClients(RobotMqtt("mqtt://127.0.0.1:1", {}), [], "test")
    clients.connect()
    assert clients.subscribe("iot/zones/advertisement", lambda *_: None) is None
    assert clients.clients == {}
