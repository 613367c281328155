"""The MQTT advertiser never blocks or raises into the sink, whatever the broker does."""

from __future__ import annotations

import socket

from mapservice.local.embedded import free_port
from mapservice.processors.advertiser import MqttAdvertiser
from mapservice.settings import Settings


def test_constructor_does_no_network_io(monkeypatch) -> None:
    """Building an advertiser opens no connection (even to an unresolvable host)."""

    def refuse(*args, **kwargs):
        raise AssertionError("network I/O in the constructor")

    monkeypatch.setattr(socket, "create_connection", refuse)
    adv = MqttAdvertiser(Settings(mqtt_url="mqtt://no-such-host.invalid:1883"))
    assert adv.topic == "iot/chunks/advertisement" and not adv.connected.is_set()


def test_publish_without_broker_queues_then_fails_counted_when_full() -> None:
    """With no broker, QoS 1 messages queue up to the bound; beyond it publish returns False."""
    adv = MqttAdvertiser(
        Settings(mqtt_url=f"mqtt://127.0.0.1:{free_port()}", advertisement_topic="ads/test"),
        max_queued=4,
    )
    adv.start()
    try:
        # Each chunk change is two messages: the 2019 topic's and its area's.
        results = [adv.publish({"row": 0, "column": i}) for i in range(4)]
        assert results == [True, True, False, False]
        assert adv.failures == 4
    finally:
        adv.stop()


def test_bad_address_does_not_raise() -> None:
    """An address that cannot be resolved is logged at start, publish returns without raising."""
    adv = MqttAdvertiser(Settings(mqtt_url="mqtt://no-such-host.invalid:1883"), max_queued=1)
    adv.start()
    try:
        assert adv.publish({"row": 0, "column": 0}) in (True, False)
    finally:
        adv.stop()
