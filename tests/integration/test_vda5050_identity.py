"""VDA 5050 vehicles under robot identities, on a real Mosquitto with the password file and
ACL `mapservice robot add <manufacturer>/<serialNumber>` writes: a vehicle publishes only
in its own topic subtree (its last will included) and reads only its own orders; the
gateway's user reads every vehicle's messages; a master control (`mapservice robot add
mapservice-master-<name>`) orders every vehicle and reads all their messages."""

from __future__ import annotations

import threading
import time

import pytest

from mapservice.adapters.mqtt_auth import GATEWAY_USER, BrokerFiles
from mapservice.adapters.mqtt_client import make_client
from mapservice.local import embedded

MASTER = "mapservice-master-plant"


@pytest.fixture
def broker(tmp_path):
    if not embedded.mosquitto_installed():
        pytest.fail("mosquitto is not installed (make system-deps installs it)")
    files = BrokerFiles(tmp_path / "passwd", tmp_path / "acl")
    creds = {name: files.add_robot(name).password for name in ("Acme/001", "Acme/002", MASTER)}
    files.set_service_user(GATEWAY_USER, "gateway-secret")
    creds[GATEWAY_USER] = "gateway-secret"
    port = embedded.free_port()
    proc = embedded.start_mosquitto(
        port,
        tmp_path,
        options=embedded.MosquittoOptions(
            password_file=files.password_file, acl_file=files.acl_file
        ),
    )
    yield port, creds
    proc.terminate()
    proc.wait(10)


class Client:
    def __init__(
        self,
        port: int,
        username: str,
        password: str,
        subscribe: str | None = None,
        will: str | None = None,
    ) -> None:
        self.received: list[tuple[str, bytes]] = []
        self.client = make_client(f"id-{username.replace('/', '-')}-{time.monotonic_ns()}")
        self.client.username_pw_set(username, password)
        if will:
            self.client.will_set(will, b'{"connectionState": "CONNECTIONBROKEN"}', qos=1)
        self.client.on_message = lambda _c, _u, m: self.received.append((m.topic, m.payload))
        granted = threading.Event()
        self.client.on_subscribe = lambda *a: granted.set()
        connected = threading.Event()
        self.client.on_connect = lambda *a: connected.set()
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        assert connected.wait(10)
        if subscribe:
            self.client.subscribe(subscribe, qos=1)
            assert granted.wait(10)

    def publish(self, topic: str, payload: bytes) -> None:
        self.client.publish(topic, payload, qos=1).wait_for_publish(10)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def test_a_vehicle_publishes_and_reads_only_its_own_subtree(broker) -> None:
    port, creds = broker
    gateway = Client(port, GATEWAY_USER, creds[GATEWAY_USER], subscribe="uagv/#")
    vehicle = Client(
        port,
        "Acme/001",
        creds["Acme/001"],
        subscribe="uagv/+/+/+/order",
        will="uagv/v2/Acme/001/connection",
    )
    master_like = Client(port, "Acme/002", creds["Acme/002"])
    for subtopic in ("state", "visualization", "connection", "factsheet"):
        vehicle.publish(f"uagv/v2/Acme/001/{subtopic}", b"own")
    vehicle.publish("uagv/v2/Acme/002/state", b"as another vehicle")
    vehicle.publish("uagv/v2/Acme/001/order", b"an order to itself")
    vehicle.publish("iot/coordinates/Acme:001", b"a 2019 pose")
    master_like.publish("uagv/v2/Acme/002/order", b"not for 001")  # a vehicle sends no orders
    vehicle.client.socket().close()  # the connection breaks: its last will is published
    vehicle.client.loop_stop()
    time.sleep(2)
    gateway.close()
    master_like.close()
    assert sorted(gateway.received) == sorted(
        [
            (f"uagv/v2/Acme/001/{s}", b"own")
            for s in ("state", "visualization", "connection", "factsheet")
        ]
        + [("uagv/v2/Acme/001/connection", b'{"connectionState": "CONNECTIONBROKEN"}')]
    )
    assert vehicle.received == []  # its own order publish was refused, another's not readable


def test_a_vehicle_cannot_read_another_vehicles_messages(broker) -> None:
    port, creds = broker
    vehicle = Client(port, "Acme/001", creds["Acme/001"], subscribe="uagv/#")
    other = Client(port, "Acme/002", creds["Acme/002"])
    other.publish("uagv/v2/Acme/002/state", b"002's state")
    time.sleep(1)
    vehicle.close()
    other.close()
    assert vehicle.received == []


def test_a_master_control_orders_every_vehicle_and_reads_their_messages(broker) -> None:
    """The master control publishes order and instantActions to each vehicle (each reads
    only its own), reads every vehicle's state and connection, and can neither speak as a
    vehicle nor write 2019 topics."""
    port, creds = broker
    gateway = Client(port, GATEWAY_USER, creds[GATEWAY_USER], subscribe="uagv/#")
    master = Client(port, MASTER, creds[MASTER], subscribe="uagv/+/+/+/state")
    master.client.subscribe("uagv/+/+/+/connection", qos=1)
    one = Client(port, "Acme/001", creds["Acme/001"], subscribe="uagv/+/+/+/order")
    one.client.subscribe("uagv/+/+/+/instantActions", qos=1)
    two = Client(port, "Acme/002", creds["Acme/002"], subscribe="uagv/+/+/+/order")
    time.sleep(0.5)  # the extra subscriptions granted
    for serial in ("001", "002"):
        master.publish(f"uagv/v2/Acme/{serial}/order", f"order for {serial}".encode())
    master.publish("uagv/v2/Acme/001/instantActions", b"pause 001")
    master.publish("uagv/v2/Acme/001/state", b"the master as a vehicle")  # refused
    master.publish("iot/coordinates/mapservice-master-plant", b"a 2019 pose")  # refused
    one.publish("uagv/v2/Acme/001/state", b"001's state")
    two.publish("uagv/v2/Acme/002/state", b"002's state")
    two.publish("uagv/v2/Acme/002/connection", b"002 online")
    deadline = time.monotonic() + 10
    while len(master.received) < 3 and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1)
    for c in (gateway, master, one, two):
        c.close()
    assert sorted(one.received) == [
        ("uagv/v2/Acme/001/instantActions", b"pause 001"),
        ("uagv/v2/Acme/001/order", b"order for 001"),
    ]
    assert two.received == [("uagv/v2/Acme/002/order", b"order for 002")]
    assert sorted(master.received) == [
        ("uagv/v2/Acme/001/state", b"001's state"),
        ("uagv/v2/Acme/002/connection", b"002 online"),
        ("uagv/v2/Acme/002/state", b"002's state"),
    ]
    # The state the master sent as vehicle 001 never reached anyone.
    states = sorted(p for t, p in gateway.received if t.endswith("/state"))
    assert states == [b"001's state", b"002's state"]


def test_master_control_names_are_checked_and_kept_in_the_acl(tmp_path) -> None:
    """The ACL names each master control (and forgets a removed one); a malformed name or
    --legacy-chunks for a master is refused with what to do."""
    files = BrokerFiles(tmp_path / "passwd", tmp_path / "acl")
    cred = files.add_robot("mapservice-master-b")
    files.add_robot("mapservice-master-a")
    files.add_robot("agv-1", legacy_chunks=True)
    assert files.master_controls() == ["mapservice-master-a", "mapservice-master-b"]
    assert files.legacy_robots() == ["agv-1"]
    assert cred.topics["publishes"] == "uagv/+/+/+/{order,instantActions}"
    assert "topic write uagv/+/+/+/instantActions" in files.acl_file.read_text()
    assert files.remove_robot("mapservice-master-b")
    assert files.master_controls() == ["mapservice-master-a"]
    with pytest.raises(ValueError, match="mapservice-master-<name>"):
        files.add_robot("mapservice-master-a/b")
    with pytest.raises(ValueError, match="legacy-chunks"):
        files.add_robot("mapservice-master-c", legacy_chunks=True)
    with pytest.raises(ValueError, match="reserved"):
        files.add_robot("mapservice-other")
