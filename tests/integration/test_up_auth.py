"""`mapservice up --auth`: the embedded stack with authentication on, as production runs it:
each simulated robot publishes with its own MQTT credential, anonymous MQTT clients and
anonymous REST writes are refused."""

from __future__ import annotations

import json
import time

import httpx
import paho.mqtt.client as mqtt
import pytest

from mapservice.adapters.mqtt_auth import read_password_file
from mapservice.adapters.mqtt_client import PollingClient
from tests.fixtures.up import Up

pytestmark = pytest.mark.integration


def connect_code(port: int, username: str | None = None, password: str | None = None) -> int:
    """The CONNACK reason of a connection attempt (0: accepted)."""
    client = PollingClient(
        mqtt.CallbackAPIVersion.VERSION2, client_id=f"probe-{time.monotonic_ns()}"
    )
    if username is not None:
        client.username_pw_set(username, password)
    codes: list[int] = []
    client.on_connect = lambda c, u, flags, reason, props: codes.append(reason.value)
    client.connect("127.0.0.1", port)
    deadline = time.monotonic() + 10
    while not codes and time.monotonic() < deadline:
        client.loop(0.1)
    client.disconnect()
    assert codes, "no CONNACK within 10 s"
    return codes[0]


@pytest.mark.timeout(300)
def test_up_auth_robots_publish_with_their_own_credentials_and_anonymous_clients_are_refused(
    tmp_path,
):
    """Two simulated robots get credentials in DATA_DIR/secrets/robots.json and their poses
    are stored; an anonymous MQTT client is refused, a robot's credential is accepted; an
    anonymous REST write gets 401; an anonymous Kafka producer writes nothing."""
    data = tmp_path / "data"
    up = Up(data, "--auth", "--robots", "2", "--history-days", "0")
    try:
        assert "anonymous clients refused" in up.output
        creds = json.loads((data / "secrets" / "robots.json").read_text())
        assert sorted(creds) == ["controller-1", "sim-000", "sim-001"]  # and the /controller page's
        assert {"sim-000", "sim-001"} <= set(read_password_file(data / "mqtt" / "passwd"))
        deadline = time.monotonic() + 90
        poses: list = []
        while time.monotonic() < deadline and not poses:
            now_ms = int(time.time() * 1000)
            reply = up.api(
                "/api/v1/poses", robotId="sim-000", **{"from": now_ms - 60_000, "to": now_ms}
            )
            poses = reply.json() if reply.status_code == 200 else []
            time.sleep(1)
        assert poses, f"no pose of sim-000 stored:\n{up.output[-3000:]}"
        assert connect_code(up.mqtt_port) != 0
        assert connect_code(up.mqtt_port, "sim-001", "wrong-password") != 0
        assert connect_code(up.mqtt_port, "sim-001", creds["sim-001"]) == 0
        assert connect_code(up.mqtt_port, "controller-1", creds["controller-1"]) == 0
        assert "type its password on" in up.output
        write = httpx.post(
            f"http://127.0.0.1:{up.api_port}/api/chunk-service/chunks",
            json={"robotId": "x"},
            timeout=30,
        )
        assert write.status_code == 401
        # Kafka serves only the components: a local producer without their credential
        # cannot write (on 4a32dd7 it wrote command events, for instance).
        assert anonymous_kafka_write(data) is not None
    finally:
        up.stop()


def anonymous_kafka_write(data):
    """The delivery error of a record an anonymous producer sends to `up`'s Kafka (None: the
    broker took it)."""
    from confluent_kafka import Producer

    properties = (data / "kafka" / "server.properties").read_text()
    advertised = next(
        line for line in properties.splitlines() if line.startswith("advertised.listeners=")
    )
    producer = Producer(
        {
            "bootstrap.servers": advertised.rsplit("//", 1)[1],
            "message.timeout.ms": 4000,
            "log_level": 0,
        }
    )
    errors: list = []
    producer.produce(
        "mapservice.command-events.v1", b"anonymous", callback=lambda e, _m: errors.append(e)
    )
    producer.flush(8)
    assert errors, "no delivery report within 8 s"
    return errors[0]
