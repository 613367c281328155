"""Through a real Mosquitto checking identities (the ACL as `mapservice up --auth` writes
it): the processors' alerts reach a master control (the plant's systems) subscribed to
`iot/incidents/+` for every kind, one that comes later gets the last alert of each kind
(retained), and a robot may neither read them nor publish a fake one."""

from __future__ import annotations

import json
import threading
import time

import paho.mqtt.client as mqtt

from mapservice.adapters.mqtt_auth import PROCESSORS_USER
from mapservice.adapters.mqtt_client import make_client
from mapservice.core.incident_model import KINDS
from mapservice.processors.advertiser import MqttAdvertiser
from mapservice.settings import Settings
from tests.fixtures.mosquitto import (
    ProbeClient,
    mosquitto_identities,  # noqa: F401 (a fixture)
)
from tests.processors.test_incident_alerts import AlertFloor, every_kind


class Subscriber:
    def __init__(self, port: int, username: str, password: str) -> None:
        self.docs: list[tuple[str, dict, bool]] = []
        self.lock = threading.Lock()
        self.client = make_client(f"sub-{time.time_ns()}", username=username, password=password)
        self.client.on_message = self._got
        subscribed = threading.Event()
        self.client.on_subscribe = lambda *_: subscribed.set()
        self.client.on_connect = lambda c, *_: c.subscribe("iot/incidents/+", qos=1)
        self.client.connect("127.0.0.1", port, keepalive=30)
        self.client.loop_start()
        assert subscribed.wait(10)

    def _got(self, _client, _userdata, message: mqtt.MQTTMessage) -> None:
        with self.lock:
            self.docs.append((message.topic, json.loads(message.payload), message.retain))

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def wait_for(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_alerts_reach_subscribers_and_robots_cannot_fake_them(
    ev,
    mosquitto_identities,  # noqa: F811 (the fixture, imported above)
) -> None:
    broker = mosquitto_identities
    # one connection per username (the broker makes the client id the username)
    reader = broker.files.add_robot("mapservice-master-plant-1")
    other = broker.files.add_robot("mapservice-master-plant-2")
    robot = broker.files.add_robot("reader-robot")
    broker.start()
    advertiser = MqttAdvertiser(
        Settings(
            mqtt_url=broker.url,
            mqtt_username=PROCESSORS_USER,
            mqtt_password=broker.service_passwords[PROCESSORS_USER],
        )
    )
    floor = AlertFloor()
    floor.mqtt = advertiser
    floor.start()
    advertiser.start()
    live = Subscriber(broker.port, "mapservice-master-plant-1", reader.password)
    try:
        assert advertiser.connected.wait(10)
        every_kind(floor, ev)
        floor.tick(11)
        floor.views.flush()
        wait_for(lambda: {d["kind"] for _, d, _ in live.docs} == set(KINDS))
        stored = {i.incident_id for i in floor.stored()}
        wait_for(lambda: stored <= {d["id"] for _, d, _ in live.docs})
        assert all(topic == f"iot/incidents/{d['kind']}" for topic, d, _ in live.docs)
        # a robot may not publish there: the broker refuses it (MQTT 5 PUBACK, not authorized)
        probe = ProbeClient(broker.port, "reader-robot", robot.password)
        try:
            fake = json.dumps({"kind": "stuck", "event": "new", "id": "fake"}).encode()
            for kind in KINDS:
                assert probe.publish(f"iot/incidents/{kind}", fake).is_failure
        finally:
            probe.client.disconnect()
            probe.client.loop_stop()
        # a late subscriber gets the last alert of each kind, retained
        with live.lock:
            last = {d["kind"]: d for _, d, _ in live.docs}
        later = Subscriber(broker.port, "mapservice-master-plant-2", other.password)
        try:
            wait_for(lambda: len(later.docs) == len(KINDS))
            assert all(retained for _, _, retained in later.docs)
            assert {d["kind"]: d for _, d, _ in later.docs} == last
        finally:
            later.close()
    finally:
        live.close()
        floor.views.close()
        advertiser.stop()
