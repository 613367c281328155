"""confluent-kafka idempotent producer behind the EventPublisher port."""

from __future__ import annotations

from collections.abc import Callable

from confluent_kafka import KafkaException, Producer

from ..settings import Settings


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


class KafkaPublisher:
    """Created without I/O; librdkafka connects lazily on the first publish."""

    def __init__(self, settings: Settings, client_id: str) -> None:
        self._producer = Producer(producer_config(settings, client_id))

    def publish(
        self, topic: str, key: bytes, value: bytes, on_done: Callable[[Exception | None], None]
    ) -> None:
        def delivered(err, _msg) -> None:
            on_done(None if err is None else KafkaException(err))

        while True:
            try:
                self._producer.produce(topic, value=value, key=key, on_delivery=delivered)
                return
            except BufferError:
                # Local queue full: serve callbacks to make room instead of dropping.
                self._producer.poll(0.05)

    def poll(self, timeout: float) -> None:
        self._producer.poll(timeout)

    def flush(self, timeout: float) -> int:
        return self._producer.flush(timeout)
