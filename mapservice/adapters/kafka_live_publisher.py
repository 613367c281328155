"""The processors' side of the live stream: stored batches' live messages, and the
incidents found in them, onto Kafka.

Best effort by design: the history is already stored when this runs and a viewer that
missed something re-seeks from the store, so a record that cannot be delivered within a
few seconds is counted and dropped, never retried, and a full local queue never blocks
the history sink.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

import structlog
from confluent_kafka import KafkaError, Message, Producer
from prometheus_client import Counter

from mapservice.adapters.kafka_logs import logged
from mapservice.core.events import Envelope
from mapservice.core.incident_model import Incident
from mapservice.core.live_incidents import incident_records
from mapservice.core.live_messages import live_records
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

LIVE_RECORDS = Counter("mapservice_live_records_total", "Live-topic records published")
LIVE_DROPPED = Counter(
    "mapservice_live_records_dropped_total",
    "Live-topic records dropped (local queue full or not delivered in time)",
)


def live_producer_config(settings: Settings, client_id: str) -> dict[str, Any]:
    return logged(
        {
            **settings.kafka_config(),
            "client.id": client_id,
            # One partition per producer keeps a processor's batches in order; a live message
            # older than a few seconds is worth nothing, so no long retries either.
            "acks": "1",
            "linger.ms": 5,
            "message.timeout.ms": 5_000,
            "queue.buffering.max.kbytes": 32 * 1024,
            "compression.type": "none",
        }
    )


class KafkaLivePublisher:
    """`publish(events)` after each stored batch; created without I/O."""

    def __init__(self, settings: Settings, client_id: str = "mapservice-processors-live") -> None:
        self.topic = settings.topic_live
        self._config = live_producer_config(settings, client_id)
        self._producer: Producer | None = None
        self._lock = threading.Lock()

    def publish(self, events: Sequence[Envelope]) -> None:
        self._produce(live_records(events))

    def publish_incidents(
        self, found: Sequence[Incident], retracted: Sequence[Incident], found_ms: int
    ) -> None:
        """Stored incident findings (called from the processors' store thread)."""
        self._produce(incident_records(found, retracted, found_ms))

    def _produce(self, records: list[bytes]) -> None:
        # The batches' records come from the event loop, the incidents' from the store
        # thread: one producer for both (librdkafka's is thread-safe), made once.
        with self._lock:
            if self._producer is None:
                self._producer = Producer(self._config)
            producer = self._producer
        for record in records:
            try:
                producer.produce(self.topic, value=record, on_delivery=self._delivered)
                LIVE_RECORDS.inc()
            except BufferError:
                LIVE_DROPPED.inc()
        producer.poll(0)  # serve earlier records' delivery callbacks

    @staticmethod
    def _delivered(err: KafkaError | None, _msg: Message) -> None:
        if err is not None:
            LIVE_DROPPED.inc()
            log.warning("live record not delivered", error=str(err))

    def close(self, timeout_s: float = 5.0) -> None:
        """Delivers what it can within `timeout_s`, drops the rest (best effort, as ever)
        and closes the producer, so that it stops dialling the brokers now."""
        producer, self._producer = self._producer, None
        if producer is not None:
            producer.flush(timeout_s)
            if len(producer):  # their delivery reports (purged) count them as dropped
                producer.purge(in_queue=True, in_flight=True, blocking=False)
                producer.poll(0)
            producer.close()
