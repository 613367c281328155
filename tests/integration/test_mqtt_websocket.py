"""The embedded brokers speak MQTT over WebSocket too: what a browser publishes there reaches
the gateway's plain MQTT subscription."""

from __future__ import annotations

import queue

import paho.mqtt.client as mqtt
import pytest

from mapservice.local import embedded


def _client(port: int, transport: str) -> mqtt.Client:
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, transport=transport)
    if transport == "websockets":
        c.ws_set_options(path="/mqtt")
    c.connect("127.0.0.1", port)
    c.loop_start()
    return c


@pytest.mark.parametrize("broker", ["amqtt", "mosquitto"])
def test_websocket_publish_reaches_tcp_subscriber(broker, tmp_path) -> None:
    """A pose published over the WebSocket listener arrives, unchanged, at a TCP subscriber."""
    port, ws_port = embedded.free_port(), embedded.free_port()
    if broker == "amqtt":
        proc = embedded.start_amqtt(port, ws_port=ws_port)
    else:
        proc = embedded.start_mosquitto(port, tmp_path, ws_port=ws_port)
    got: queue.Queue = queue.Queue()
    subscribed: queue.Queue = queue.Queue()
    sub = _client(port, "tcp")
    sub.on_message = lambda c, u, m: got.put((m.topic, m.payload))
    sub.on_subscribe = lambda *a: subscribed.put(True)
    sub.subscribe("iot/coordinates/#", qos=1)
    subscribed.get(timeout=10)
    pub = _client(ws_port, "websockets")
    try:
        payload = b'{"robotId":"browser-1"}'
        pub.publish("iot/coordinates/browser-1", payload, qos=1).wait_for_publish(10)
        assert got.get(timeout=10) == ("iot/coordinates/browser-1", payload)
    finally:
        for c in (pub, sub):
            c.loop_stop()
            c.disconnect()
        embedded.stop(proc)
