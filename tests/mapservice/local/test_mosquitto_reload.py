"""The local Mosquitto: a new robot credential while it runs, and the largest message, never
cost a message queued for the gateway's persistent session."""

from __future__ import annotations

import threading
import time

import paho.mqtt.client as mqtt
import pytest

from mapservice.adapters.mqtt_auth import GATEWAY_USER
from mapservice.adapters.mqtt_client import PollingClient
from mapservice.local import embedded
from mapservice.local.stack import Stack

pytestmark = pytest.mark.skipif(not embedded.mosquitto_installed(), reason="needs mosquitto")


class Session:
    """A persistent (clean_session=False) subscriber, as the gateway is."""

    def __init__(
        self, port: int, client_id: str, username: str | None = None, password: str | None = None
    ) -> None:
        self.port, self.client_id = port, client_id
        self.username, self.password = username, password
        self.received: list[bytes] = []
        self.client: mqtt.Client | None = None

    def connect(self) -> None:
        connected = threading.Event()
        client = PollingClient(
            mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id, clean_session=False
        )
        if self.username:
            client.username_pw_set(self.username, self.password)
        client.on_connect = lambda c, u, f, reason, p: connected.set()
        client.on_message = lambda c, u, message: self.received.append(message.payload)
        client.connect("127.0.0.1", self.port)
        client.loop_start()
        assert connected.wait(10), "no CONNACK"
        self.client = client

    def disconnect(self) -> None:
        assert self.client is not None
        self.client.disconnect()
        self.client.loop_stop()
        self.client = None

    def wait_for(self, count: int, timeout_s: float = 10) -> int:
        deadline = time.monotonic() + timeout_s
        while len(self.received) < count and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # anything more (a duplicate) shows up now
        return len(self.received)


def publish_acknowledged(
    port: int,
    topic: str,
    payloads: list[bytes],
    username=None,
    password=None,
    client_id="publisher",
) -> None:
    client = PollingClient(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
    if username:
        client.username_pw_set(username, password)
    client.connect("127.0.0.1", port)
    client.loop_start()
    try:
        for payload in payloads:
            client.publish(topic, payload, qos=1).wait_for_publish(10)  # its PUBACK
    finally:
        client.disconnect()
        client.loop_stop()


def test_a_robot_added_while_the_restarted_broker_runs_loses_no_queued_message(tmp_path):
    """As `up --auth` restarted and then `robot add`: the broker starts from its store with
    the gateway's session offline, a robot is added (its credential in force at once), the
    robot publishes 20 QoS 1 messages, the gateway reconnects: it gets all 20. (Reloading
    by SIGHUP, Mosquitto 2.0.11 delivered none of them.)"""
    stack = Stack(tmp_path, mqtt="mosquitto", mqtt_auth=True)
    try:
        stack.start_mqtt()
        gateway = Session(
            stack.mqtt_port, GATEWAY_USER, GATEWAY_USER, stack.service_password(GATEWAY_USER)
        )
        gateway.connect()
        gateway.client.subscribe("iot/coordinates/#", qos=1)
        time.sleep(0.5)
        gateway.disconnect()
        stack.start_mqtt()  # what the next `up` does: the broker starts from its store
        credential = stack.add_robot("robot-added-late")
        payloads = [f"pose {i}".encode() for i in range(20)]
        publish_acknowledged(
            stack.mqtt_port,
            "iot/coordinates/robot-added-late",
            payloads,
            credential.username,
            credential.password,
            credential.username,
        )
        gateway.connect()
        assert gateway.wait_for(20) == 20
        assert sorted(gateway.received) == sorted(payloads)
        gateway.disconnect()
    finally:
        stack.stop()


def test_the_brokers_message_size_limit_follows_the_gateways_maximum(tmp_path):
    """Mosquitto's `message_size_limit` is BROKER_SIZE_HEADROOM x `max_message_bytes` (the
    gateway's limit): a payload over the gateway's limit but within that reaches the
    gateway's session (which dead-letters it as oversized), one byte more is dropped by the
    broker (it is not queued or stored)."""
    from mapservice.local.stack_mqtt import BROKER_SIZE_HEADROOM

    limit = BROKER_SIZE_HEADROOM * 4096
    stack = Stack(tmp_path, mqtt="mosquitto", extra_env={"MAPSERVICE_MAX_MESSAGE_BYTES": "4096"})
    try:
        stack.start_mqtt()
        assert (
            f"message_size_limit {limit}"
            in (tmp_path / f"mosquitto-{stack.mqtt_port}.conf").read_text()
        )
        gateway = Session(stack.mqtt_port, "mapservice-gateway")
        gateway.connect()
        gateway.client.subscribe("iot/coordinates/#", qos=1)
        time.sleep(0.3)
        publish_acknowledged(stack.mqtt_port, "iot/coordinates/r1", [b"x" * (limit + 1)])
        publish_acknowledged(stack.mqtt_port, "iot/coordinates/r1", [b"y" * limit])
        publish_acknowledged(stack.mqtt_port, "iot/coordinates/r1", [b"z" * 4097])
        assert gateway.wait_for(2) == 2
        assert gateway.received == [b"y" * limit, b"z" * 4097]
        gateway.disconnect()
    finally:
        stack.stop()
