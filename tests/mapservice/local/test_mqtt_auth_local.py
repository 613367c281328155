"""The local stack's robot identities: Mosquitto's configuration, and why amqtt is not used
for them."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest

from mapservice.adapters.mqtt_client import make_client
from mapservice.local import embedded
from mapservice.local.certs import make_server_cert
from mapservice.local.stack import Stack


def test_mosquitto_conf_with_auth_and_tls(tmp_path):
    """With identities: no anonymous client, the password file and ACL, client id = username;
    with TLS: a second listener with the local CA's server certificate."""
    certs = make_server_cert(tmp_path / "tls")
    options = embedded.MosquittoOptions(
        tmp_path / "passwd", tmp_path / "acl", tmp_path / "acl.dynsec.json", 8883, certs
    )
    lines = embedded.mosquitto_conf(1883, 9001, options).splitlines()
    for expected in (
        f"plugin {embedded.dynsec_plugin()}",
        f"plugin_opt_config_file {tmp_path / 'acl.dynsec.json'}",
        "allow_anonymous false",
        f"password_file {tmp_path / 'passwd'}",
        f"acl_file {tmp_path / 'acl'}",
        "use_username_as_clientid true",
        "per_listener_settings false",
        "listener 8883 127.0.0.1",
        f"certfile {certs.cert_file}",
        f"cafile {certs.ca_file}",
    ):
        assert expected in lines
    assert "allow_anonymous true" not in lines
    plain = embedded.mosquitto_conf(1883).splitlines()
    assert "allow_anonymous true" in plain and not any(
        line.startswith("password_file") for line in plain
    )


def test_auth_stack_needs_mosquitto(tmp_path):
    """Identities or TLS on the embedded amqtt are refused with the reason."""
    for flags in ({"mqtt_auth": True}, {"mqtt_tls": True}):
        with pytest.raises(ValueError, match="Mosquitto"):
            Stack(tmp_path, mqtt="amqtt", **flags)


def test_component_credentials(tmp_path):
    """The gateway gets its service user, the processors theirs, robots and tools none; with TLS
    every component connects to the TLS listener trusting the local CA."""
    stack = Stack(tmp_path, mqtt="mosquitto", mqtt_auth=True, mqtt_tls=True)
    gateway, server, sim = stack.env("gateway"), stack.env("server"), stack.env("sim")
    assert gateway["MAPSERVICE_MQTT_USERNAME"] == "mapservice-gateway"
    assert server["MAPSERVICE_MQTT_USERNAME"] == "mapservice-processors"
    assert gateway["MAPSERVICE_MQTT_PASSWORD"] != server["MAPSERVICE_MQTT_PASSWORD"]
    assert sim.get("MAPSERVICE_MQTT_USERNAME") is None  # robots use their own (--credentials)
    assert gateway["MAPSERVICE_MQTT_URL"] == stack.mqtts_url
    assert (
        gateway["MAPSERVICE_MQTT_CA_FILE"]
        == server["MAPSERVICE_MQTT_CA_FILE"]
        == str(stack.ca_file)
    )
    # The generated passwords are kept: a restarted stack uses the same.
    again = Stack(tmp_path, mqtt="mosquitto", mqtt_auth=True)
    assert again.env("gateway")["MAPSERVICE_MQTT_PASSWORD"] == gateway["MAPSERVICE_MQTT_PASSWORD"]


AMQTT = """
import asyncio
from amqtt.broker import Broker

async def main():
    broker = Broker({{"listeners": {{"default": {{"type": "tcp", "bind": "127.0.0.1:{port}"}}}},
                     "plugins": {{"amqtt.plugins.authentication.AnonymousAuthPlugin":
                                  {{"allow_anonymous": False}}}}}})
    await broker.start()
    await asyncio.Event().wait()

asyncio.run(main())
"""


def test_amqtt_lets_an_unauthenticated_client_wipe_a_session():
    """Why identities need Mosquitto: on amqtt 0.12 an anonymous client that the broker refuses
    still deletes the persistent session of the client id it names (the gateway's), so what
    was queued for the gateway and its subscription are gone. If this test fails, amqtt has
    fixed it and the local stack could offer identities on amqtt too."""
    port = embedded.free_port()
    proc = subprocess.Popen(
        [sys.executable, "-c", AMQTT.format(port=port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        embedded.wait_for_port(port, proc=proc, what="amqtt")
        got: list[bytes] = []

        def connect(client_id, clean, user):
            client = make_client(
                client_id, clean_session=clean, username=user, password="x" if user else None
            )
            answered = threading.Event()
            client.on_connect = lambda *_: answered.set()
            client.on_message = lambda _c, _u, m: got.append(m.payload)
            client.connect("127.0.0.1", port)
            client.loop_start()
            assert answered.wait(5)
            return client

        gateway = connect("gateway", False, "gw")
        gateway.subscribe("t/#", 1)
        time.sleep(0.5)
        gateway.disconnect()
        gateway.loop_stop()
        robot = connect("robot", True, "robot")
        robot.publish("t/1", b"queued for the gateway", qos=1).wait_for_publish(5)
        attacker = connect("gateway", True, None)  # refused: Not authorized
        time.sleep(0.5)
        attacker.loop_stop()
        gateway = connect("gateway", False, "gw")
        robot.publish("t/1", b"after", qos=1).wait_for_publish(5)
        time.sleep(1.0)
        assert got == []  # neither the queued message nor a new one: the session was wiped
        gateway.loop_stop()
        robot.loop_stop()
    finally:
        proc.terminate()
        proc.wait(10)
