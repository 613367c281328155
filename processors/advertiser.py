"""Publishes the chunk advertisements over MQTT (paho, its own network thread): each change
on the 2019 topic and on its area's topic (core/areas.py), encoded once.

The sink must never wait for or fail because of MQTT: `publish` only queues (bounded),
and a broker that is down, slow or refusing costs a logged, counted failure, not a stuck
or crashed sink. Advertisements are hints (robots also download the whole map at start),
so what is lost while the broker is away is not replayed.
"""

from __future__ import annotations

import os
import socket
import threading
import time

import msgspec
import paho.mqtt.client as mqtt
import structlog
from prometheus_client import Counter

from mapservice.adapters.mqtt_client import parse_mqtt_url, service_client
from mapservice.core.areas import AdvertisementTopics, AreaGrid
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

ADVERTISED = Counter(
    "mapservice_advertisements_total", "Chunk advertisements handed to the MQTT client", ["result"]
)

_json = msgspec.json.Encoder()


class MqttAdvertiser:
    """Constructing it does no I/O; `start()` connects in the background."""

    def __init__(self, settings: Settings, *, qos: int = 1, max_queued: int = 10_000) -> None:
        self.topic = settings.advertisement_topic
        self.topics = AdvertisementTopics(
            settings.advertisement_topic,
            AreaGrid(settings.advertisement_area_chunks),
            settings.advertise_on_2019_topic,
        )
        self.host, self.port, _tls = parse_mqtt_url(settings.mqtt_url)
        self.qos = qos
        self.client = service_client(
            settings,
            f"mapservice-advertiser-{socket.gethostname()}-{os.getpid()}",
            clean_session=True,
        )
        self.client.max_queued_messages_set(max_queued)
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = self._on_disconnect
        self.connected = threading.Event()
        self._started = False
        self.failures = 0
        self._last_warning = -1e9

    def start(self) -> None:
        if self._started:
            return
        self._started = True
        try:
            self.client.connect_async(self.host, self.port, keepalive=30)
            self.client.loop_start()  # reconnects by itself
        except Exception as exc:  # a bad address must not stop the processors
            log.error(
                "advertiser could not start", error=str(exc), broker=f"{self.host}:{self.port}"
            )

    def publish(self, payload: dict) -> bool:
        """Queues one chunk advertisement on its topics (the 2019 one, its area's); False
        (logged, counted) if any could not be queued."""
        encoded = _json.encode(payload)
        results = [
            self._queue(topic, encoded)
            for topic in self.topics.for_chunk(payload["row"], payload["column"])
        ]
        return all(results)

    def publish_to(self, topic: str, payload: dict, retain: bool = False) -> bool:
        """Queues one document on `topic` (chunks', zones' advertisements, incident alerts),
        retained by the broker if asked; as `publish`."""
        return self._queue(topic, _json.encode(payload), retain)

    def _queue(self, topic: str, encoded: bytes, retain: bool = False) -> bool:
        try:
            rc = self.client.publish(topic, encoded, qos=self.qos, retain=retain).rc
            error = mqtt.error_string(rc)
        except Exception as exc:  # never let MQTT trouble reach the sink
            rc, error = -1, str(exc)
        # Not connected yet (or reconnecting): paho keeps a QoS 1 message and sends it later.
        offline = rc == mqtt.MQTT_ERR_NO_CONN and self.qos > 0
        ok = rc == mqtt.MQTT_ERR_SUCCESS or offline
        ADVERTISED.labels("queued_offline" if offline else "queued" if ok else "failed").inc()
        if not ok:
            self.failures += 1
            now = time.monotonic()
            if now - self._last_warning > 10:  # a broker outage must not flood the log
                self._last_warning = now
                log.warning(
                    "advertisement not published", error=error, topic=topic, failures=self.failures
                )
        return ok

    def stop(self) -> None:
        if not self._started:
            return
        self._started = False
        try:
            self.client.disconnect()
            self.client.loop_stop()
        except Exception as exc:
            log.warning("advertiser stop", error=str(exc))

    def _on_connect(self, client, userdata, flags, reason_code, properties=None) -> None:
        if reason_code.is_failure:
            log.error("advertiser connection refused", reason=str(reason_code))
            return
        self.connected.set()
        log.info("advertiser connected", broker=f"{self.host}:{self.port}", topic=self.topic)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties=None) -> None:
        self.connected.clear()
        if self._started:
            log.warning("advertiser disconnected; paho reconnects", reason=str(reason_code))
