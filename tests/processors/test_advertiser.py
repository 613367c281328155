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


def test_a_change_is_encoded_once_and_queued_on_the_2019_topic_and_its_areas(monkeypatch) -> None:
    """Generated chunks and area sizes: one encode per change, the same bytes queued on the
    2019 topic (unless turned off) and on the topic of the area holding the chunk."""
    import random
    from types import SimpleNamespace

    import paho.mqtt.client as mqtt

    from mapservice.processors import advertiser as module

    encodes: list[dict] = []

    class CountingEncoder:
        def encode(self, payload: dict) -> bytes:
            encodes.append(payload)
            return repr(payload).encode()

    class RecordingClient:
        def __init__(self) -> None:
            self.queued: list[tuple[str, bytes]] = []

        def publish(
            self, topic: str, payload: bytes, qos: int, retain: bool = False
        ) -> SimpleNamespace:
            self.queued.append((topic, payload))
            return SimpleNamespace(rc=mqtt.MQTT_ERR_SUCCESS)

    monkeypatch.setattr(module, "_json", CountingEncoder())
    rng = random.Random(9)
    for _ in range(200):
        n, on_2019 = rng.randint(1, 6), rng.random() < 0.5
        adv = MqttAdvertiser(Settings(advertisement_area_chunks=n, advertise_on_2019_topic=on_2019))
        adv.client = RecordingClient()  # type: ignore[assignment]
        row, column = rng.randint(0, 40), rng.randint(0, 40)
        encodes.clear()
        assert adv.publish({"row": row, "column": column})
        area = f"iot/chunks/advertisement/area/{row // n}/{column // n}"
        expected = (["iot/chunks/advertisement"] if on_2019 else []) + [area]
        queued = adv.client.queued  # type: ignore[attr-defined]
        assert [t for t, _ in queued] == expected
        assert len(encodes) == 1 and len({p for _, p in queued}) == 1
