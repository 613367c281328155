"""confluent-kafka idempotent producer behind the EventPublisher port."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from confluent_kafka import KafkaError, KafkaException, Producer

from mapservice.settings import Settings


def producer_config(settings: Settings, client_id: str) -> dict:
    return {
        **settings.kafka_config(),
        "client.id": client_id,
        "enable.idempotence": True,
        "acks": "all",
        # 50 ms batches several events per partition: at 1,000 robots this cut the CPU
        # per event of tansu by ~2/3 and of the gateway by ~1/5 (BENCHMARKS.md).
        "linger.ms": 50,
        "compression.type": "none",  # aiokafka (faust) lacks lz4 without extras; chunks are zlib already
        # Same partition for the same key as faust/aiokafka producers.
        "partitioner": "murmur2_random",
        "message.timeout.ms": 30_000,
    }


class RecordTooLarge(ValueError):
    """Kafka refuses a record this large (librdkafka's message.max.bytes)."""


class KafkaPublisher:
    """Created without I/O: librdkafka starts connecting as soon as a Producer exists, so
    the Producer is made on the first publish (an API that never takes a 2019 POST never
    dials Kafka, nor logs that it cannot reach it)."""

    def __init__(self, settings: Settings, client_id: str) -> None:
        self._config = producer_config(settings, client_id)
        self._producer: Producer | None = None
        self._lock = threading.Lock()

    @property
    def connected(self) -> bool:
        """Whether a Producer exists yet (it does from the first publish on)."""
        return self._producer is not None

    def _get(self) -> Producer:
        if self._producer is None:
            with self._lock:
                if self._producer is None:
                    self._producer = Producer(self._config)
        return self._producer

    def publish(
        self, topic: str, key: bytes, value: bytes, on_done: Callable[[Exception | None], None]
    ) -> None:
        def delivered(err, _msg) -> None:
            on_done(None if err is None else KafkaException(err))

        producer = self._get()
        while True:
            try:
                producer.produce(topic, value=value, key=key, on_delivery=delivered)
                return
            except BufferError:
                # Local queue full: serve callbacks to make room instead of dropping.
                producer.poll(0.05)
            except KafkaException as exc:
                if exc.args and exc.args[0].code() == KafkaError.MSG_SIZE_TOO_LARGE:
                    raise RecordTooLarge(f"{len(value)} bytes: larger than Kafka takes") from None
                raise

    def poll(self, timeout: float) -> None:
        if self._producer is None:
            time.sleep(timeout)  # nothing published yet: nothing to deliver
        else:
            self._producer.poll(timeout)

    def flush(self, timeout: float) -> int:
        return 0 if self._producer is None else self._producer.flush(timeout)
