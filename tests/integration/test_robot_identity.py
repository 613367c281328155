"""Robot identities against a real Mosquitto with a password file, an ACL and a TLS listener
(the gateway and the processors connect over TLS with their service users): robots publish
only as themselves, the gateway refuses payloads naming another robot, anonymous clients
are refused, and what a robot sends as itself is stored."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import httpx
import paho.mqtt.client as mqtt
import pytest

from mapservice.adapters.mqtt_client import MqttTls, make_client, parse_mqtt_url
from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.core.events import decode_dead_letter
from mapservice.core.wire2019 import encode_chunk_create, encode_coordinates, format_timestamp
from mapservice.local.stack import Stack
from mapservice.local.stack_mqtt import mqtt_accepts
from mapservice.robot.connection import RobotMqtt, load_credentials
from mapservice.robot.loadgen import RobotFleet
from mapservice.robot.simrun import SimRunner
from mapservice.runtime.secrets import OPERATOR_TOKEN_FILE, stored_secret
from tests.fixtures.paths import MAPS, ROOT

from .conftest import read_topic, run_stack, stored_keys, wait_for_count

PIXELS = bytes(range(100)) * 100  # one 100 x 100 chunk of the depot map


def now_ms() -> int:
    return time.time_ns() // 1_000_000


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = Stack(
        tmp_path_factory.mktemp("stack-identity"), mqtt="mosquitto", mqtt_auth=True, mqtt_tls=True
    )
    yield run_stack(stack, meta_for(load_ros_map(MAPS / "depot.yaml")))
    stack.stop()


@pytest.fixture(scope="module")
def robots(stack):
    return {
        name: stack.add_robot(f"id-{name}", legacy_chunks=(name == "legacy"))
        for name in ("a", "b", "legacy")
    }


class Robot:
    """One robot's own MQTT connection (paho, QoS 1), with what it received."""

    def __init__(
        self,
        url: str,
        username: str | None,
        password: str | None,
        *,
        client_id: str | None = None,
        protocol: int = mqtt.MQTTv311,
        tls: MqttTls | None = None,
    ) -> None:
        host, port, use_tls = parse_mqtt_url(url)
        self.client = make_client(
            client_id or f"test-{username}-{now_ms()}",
            username=username,
            password=password,
            tls=use_tls,
            tls_files=tls,
            protocol=protocol,
        )
        self.received: list[tuple[str, bytes]] = []
        self.puback: dict[int, str] = {}
        self.subscribed = threading.Event()
        connected = threading.Event()
        self.client.on_connect = lambda *_: connected.set()
        self.client.on_message = lambda _c, _u, m: self.received.append((m.topic, m.payload))
        self.client.on_publish = lambda _c, _u, mid, rc, _p: self.puback.__setitem__(mid, str(rc))
        self.client.on_subscribe = lambda *_: self.subscribed.set()
        self.client.connect(host, port, keepalive=30)
        self.client.loop_start()
        assert connected.wait(10), f"{username} could not connect to {url}"

    def publish(self, topic: str, payload: bytes) -> mqtt.MQTTMessageInfo:
        info = self.client.publish(topic, payload, qos=1)
        info.wait_for_publish(10)
        return info

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def pose(robot_id: str, ts_ms: int, x: float = 1.0) -> bytes:
    return encode_coordinates(robot_id, format_timestamp(ts_ms), x, 2.0, battery_level=50.0)


def chunk(robot_id: str, ts_ms: int, row: int = 1, column: int = 1) -> bytes:
    return encode_chunk_create(row, column, PIXELS, format_timestamp(ts_ms), robot_id)


def dead_letters(stack: Stack) -> list:
    return [
        decode_dead_letter(v)
        for v in read_topic(stack, stack.settings().topic_dead_letter, 1, timeout_s=5)
    ]


def test_anonymous_and_wrong_credentials_are_refused(stack, robots):
    """An anonymous client, a wrong password and an unknown user cannot connect, on the plain
    and on the TLS listener; a robot's own credential can, on both."""
    a = robots["a"]
    tls = {"tls_files": MqttTls(stack.ca_file)}
    for url, extra in ((stack.mqtt_url, {}), (stack.mqtts_url, tls)):
        assert not mqtt_accepts(url, None, None, **extra)
        assert not mqtt_accepts(url, a.username, "not-the-password", **extra)
        assert not mqtt_accepts(url, "nobody", a.password, **extra)
        assert mqtt_accepts(url, a.username, a.password, **extra)


def test_tls_listener_needs_the_ca(stack, robots):
    """A client that does not trust the local CA cannot talk to the TLS listener (the
    certificate check fails), so the gateway's mqtts:// hop really is verified TLS."""
    a = robots["a"]
    with pytest.raises(Exception, match="CERTIFICATE_VERIFY_FAILED"):
        make_client("no-ca", username=a.username, password=a.password, tls=True).connect(
            *parse_mqtt_url(stack.mqtts_url)[:2]
        )
    assert gateway_connected(stack)
    assert stack.env("gateway")["MAPSERVICE_MQTT_URL"] == stack.mqtts_url


def gateway_connected(stack: Stack, timeout_s: float = 15) -> bool:
    """Whether the gateway says it is connected to the broker within `timeout_s`: the
    `robots` fixture restarted the broker for each new user, and the gateway reconnects
    after its back-off."""
    deadline = time.monotonic() + timeout_s
    while True:
        ready = httpx.get(f"http://127.0.0.1:{stack.health_port}/readyz", timeout=5).json()
        if ready["mqtt_connected"] is True or time.monotonic() > deadline:
            return ready["mqtt_connected"] is True
        time.sleep(0.2)


def test_robot_own_pose_and_chunk_are_stored(stack, robots):
    """Robot A's pose on iot/coordinates/A and chunk on iot/chunks/create/A (its own topics,
    its own robotId), over the plain and the TLS listener, are stored as robot A's."""
    a = robots["a"]
    start = now_ms() - 5_000
    # One connection at a time: the broker makes a robot's client id its username, so a
    # second connection of robot A would replace the first.
    secure = Robot(stack.mqtts_url, a.username, a.password, tls=MqttTls(stack.ca_file))
    try:
        assert secure.publish(a.topics["pose"], pose(a.robot_id, start)).is_published()
        assert secure.publish(a.topics["chunks"], chunk(a.robot_id, start)).is_published()
    finally:
        secure.close()
    plain = Robot(stack.mqtt_url, a.username, a.password)
    try:
        assert plain.publish(a.topics["pose"], pose(a.robot_id, start + 1)).is_published()
    finally:
        plain.close()
    poses = wait_for_count(stack, "pose", a.robot_id, start - 1, start + 10, 2)
    chunks = wait_for_count(stack, "chunk", a.robot_id, start - 1, start + 10, 1)
    assert sorted(poses) == [(a.robot_id, start), (a.robot_id, start + 1)]
    assert chunks == [(a.robot_id, start)]


def test_advertisements_reach_robots_under_auth(stack, robots):
    """The processors publish advertisements as their service user and every robot may read
    them: robot B, subscribed, hears of the chunk robot A wrote."""
    a, b = robots["a"], robots["b"]
    listener = Robot(stack.mqtt_url, b.username, b.password)
    try:
        listener.client.subscribe(b.topics["advertisements"], 1)
        assert listener.subscribed.wait(5)
        ts = now_ms() - 500
        writer = Robot(stack.mqtt_url, a.username, a.password)
        try:
            writer.publish(a.topics["chunks"], chunk(a.robot_id, ts, row=2, column=2))
        finally:
            writer.close()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not any(
            a.robot_id.encode() in p for _, p in listener.received
        ):
            time.sleep(0.1)
        assert any(
            t == b.topics["advertisements"] and a.robot_id.encode() in p
            for t, p in listener.received
        )
    finally:
        listener.close()


def test_zone_advertisements_reach_robots_under_auth(stack, robots):
    """An operator draws a zone; the processors advertise it as their service user on the
    zone topic and every robot may read it (how the simulated robots learn zones)."""
    b = robots["b"]
    topic = "iot/zones/advertisement"
    listener = Robot(stack.mqtt_url, b.username, b.password)
    try:
        listener.client.subscribe(topic, 1)
        assert listener.subscribed.wait(5)
        token = stored_secret(stack.data_dir, OPERATOR_TOKEN_FILE)
        r = httpx.post(
            f"{stack.api_url}/api/v1/annotations",
            timeout=30,
            headers={"Authorization": f"Bearer {token}"},
            json={
                "id": "zone-under-auth",
                "shape": "zone",
                "name": "spill",
                "kind": "keep_out",
                "polygon": [[1, 1], [2, 1], [2, 2]],
            },
        )
        assert r.status_code == 201, r.text
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not any(
            b"zone-under-auth" in p for _, p in listener.received
        ):
            time.sleep(0.1)
        assert any(t == topic and b"zone-under-auth" in p for t, p in listener.received)
    finally:
        listener.close()


def test_robot_a_cannot_publish_as_robot_b(stack, robots):
    """Robot A publishing on robot B's topics: with MQTT 3.1.1 the broker acknowledges and
    drops it (the gateway never sees it: no row, no dead letter); with MQTT 5 its PUBACK says
    Not authorized. A's own marker published afterwards is stored, so the drop is not a delay."""
    a, b = robots["a"], robots["b"]
    ts = now_ms() - 3_000
    robot = Robot(stack.mqtt_url, a.username, a.password)
    try:
        forged = [
            robot.publish(b.topics["pose"], pose(b.robot_id, ts)),
            robot.publish(b.topics["chunks"], chunk(b.robot_id, ts)),
            robot.publish(f"iot/coordinates/{b.robot_id}", pose(a.robot_id, ts)),
        ]
        assert all(info.is_published() for info in forged)  # QoS 1 acknowledged, silently dropped
        assert robot.publish(a.topics["pose"], pose(a.robot_id, ts + 7)).is_published()
    finally:
        robot.close()
    v5 = Robot(stack.mqtt_url, a.username, a.password, protocol=mqtt.MQTTv5)
    try:
        refused = v5.publish(b.topics["pose"], pose(b.robot_id, ts + 1))
        allowed = v5.publish(a.topics["pose"], pose(a.robot_id, ts + 8))
        deadline = time.monotonic() + 5
        while len(v5.puback) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert v5.puback[refused.mid] == "Not authorized"
        assert v5.puback[allowed.mid] == "Success"
    finally:
        v5.close()
    assert wait_for_count(stack, "pose", a.robot_id, ts + 7, ts + 9, 2) == [
        (a.robot_id, ts + 7),
        (a.robot_id, ts + 8),
    ]
    assert stored_keys(stack, "pose", b.robot_id, ts - 1, ts + 10) == []
    assert stored_keys(stack, "chunk", b.robot_id, ts - 1, ts + 10) == []
    assert not [d for d in dead_letters(stack) if b.robot_id in d.mqtt_topic]


def test_payload_naming_another_robot_is_a_dead_letter(stack, robots):
    """Robot A on its own topics with a payload saying robotId B: the broker lets it through,
    the gateway dead-letters it as robot_id_mismatch (pose and per-robot chunk alike)."""
    a, b = robots["a"], robots["b"]
    ts = now_ms() - 2_000
    robot = Robot(stack.mqtt_url, a.username, a.password)
    try:
        robot.publish(a.topics["pose"], pose(b.robot_id, ts))
        robot.publish(a.topics["chunks"], chunk(b.robot_id, ts))
    finally:
        robot.close()
    deadline, mine = time.monotonic() + 30, []
    while time.monotonic() < deadline and len(mine) < 2:
        mine = [
            d
            for d in dead_letters(stack)
            if d.mqtt_topic in (a.topics["pose"], a.topics["chunks"])
            and b.robot_id.encode() in d.payload
        ]
    assert sorted(d.mqtt_topic for d in mine) == sorted([a.topics["pose"], a.topics["chunks"]])
    assert all(d.reason == "robot_id_mismatch" and repr(b.robot_id) in d.detail for d in mine)
    assert stored_keys(stack, "pose", b.robot_id, ts - 1, ts + 1) == []


def test_legacy_chunk_topic_is_closed_unless_opened_for_a_robot(stack, robots):
    """Under auth the 2019 topic iot/chunks/create is refused to a robot (dropped by the broker),
    and open to one added with --legacy-chunks, whose chunk is stored."""
    a, legacy = robots["a"], robots["legacy"]
    ts = now_ms() - 1_000
    for cred, row in ((a, 2), (legacy, 3)):
        robot = Robot(stack.mqtt_url, cred.username, cred.password)
        try:
            assert robot.publish(
                "iot/chunks/create", chunk(cred.robot_id, ts, row=row)
            ).is_published()
        finally:
            robot.close()
    assert wait_for_count(stack, "chunk", legacy.robot_id, ts, ts + 1, 1) == [(legacy.robot_id, ts)]
    assert stored_keys(stack, "chunk", a.robot_id, ts, ts + 1) == []


def test_robot_cannot_read_others_or_take_the_gateway_session(stack, robots):
    """Robot A subscribed to `#` receives nothing of robot B's messages; connecting with the
    gateway's client id gets A its own session (client id = username), and the gateway keeps
    its session: B's next pose is stored."""
    a, b = robots["a"], robots["b"]
    spy = Robot(stack.mqtt_url, a.username, a.password, client_id=stack.settings().mqtt_client_id)
    try:
        spy.client.subscribe([("#", 1), ("iot/coordinates/#", 1)])
        assert spy.subscribed.wait(5)
        ts = now_ms() - 1_000
        robot_b = Robot(stack.mqtt_url, b.username, b.password)
        try:
            robot_b.publish(b.topics["pose"], pose(b.robot_id, ts))
        finally:
            robot_b.close()
        assert wait_for_count(stack, "pose", b.robot_id, ts, ts + 1, 1) == [(b.robot_id, ts)]
        assert spy.received == []
    finally:
        spy.close()
    ready = httpx.get(f"http://127.0.0.1:{stack.health_port}/readyz", timeout=5).json()
    assert ready["mqtt_connected"] is True


def test_robot_add_command_gives_a_working_credential(stack, tmp_path):
    """`mapservice robot add` on the stack's data dir writes the files (a running
    `up` then restarts its Mosquitto to read them), prints the credential and saves it; the
    robot can then connect."""
    creds = tmp_path / "robots.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "robot",
            "add",
            "id-cli",
            "--data-dir",
            str(stack.data_dir),
            "--save",
            str(creds),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    password = load_credentials(creds)["id-cli"]
    assert f"password   {password}" in done.stdout and "iot/chunks/create/id-cli" in done.stdout
    assert "restart" in done.stdout and "SIGHUP" not in done.stdout.replace("not SIGHUP", "")
    deadline = time.monotonic() + 10
    # What `up`'s loop does twice a second: restart the broker once the files held still.
    while not mqtt_accepts(stack.mqtt_url, "id-cli", password):
        stack.reload_mqtt_if_files_changed()
        assert time.monotonic() < deadline, "the new robot was never accepted"
        time.sleep(0.5)
    again = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "robot",
            "add",
            "id-cli",
            "--data-dir",
            str(stack.data_dir),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert again.returncode != 0 and "--rotate" in again.stderr


def test_simulated_robots_use_their_own_credentials(stack):
    """The shift simulator and the 2019 load generator, given a credentials file, connect each
    robot as itself and publish chunks on its own chunk topic: their poses and chunks are stored."""
    ros_map = load_ros_map(MAPS / "depot.yaml")
    creds = {f"idsim-{i:03d}": stack.add_robot(f"idsim-{i:03d}").password for i in range(2)}
    creds |= {f"idload-{i:04d}": stack.add_robot(f"idload-{i:04d}").password for i in range(2)}
    conn = RobotMqtt(stack.mqtts_url, creds, MqttTls(stack.ca_file))
    start = now_ms()
    sim = SimRunner(stack.mqtts_url, ros_map, 2, prefix="idsim", mqtt_conn=conn)
    fleet = RobotFleet(
        stack.mqtt_url,
        ros_map,
        2,
        prefix="idload",
        chunk_period_s=2.0,
        mqtt_conn=RobotMqtt(stack.mqtt_url, creds),
    )
    runner = threading.Thread(target=sim.run, args=(6.0,))
    runner.start()
    stats = fleet.run(6.0)
    runner.join(30)
    assert sim.stats.errors == 0 and sim.stats.poses >= 6 and stats.chunks >= 2
    end = now_ms() + 1_000
    sim_poses = wait_for_count(stack, "pose", "idsim-", start - 1_000, end, sim.stats.poses)
    load_poses = wait_for_count(stack, "pose", "idload-", start - 1_000, end, stats.poses)
    load_chunks = wait_for_count(stack, "chunk", "idload-", start - 1_000, end, stats.chunks)
    assert len(sim_poses) == sim.stats.poses
    assert (len(load_poses), len(load_chunks)) == (stats.poses, stats.chunks)
    with pytest.raises(ValueError, match="no credential"):
        RobotFleet(
            stack.mqtt_url, ros_map, 3, prefix="idload", mqtt_conn=RobotMqtt(stack.mqtt_url, creds)
        )
