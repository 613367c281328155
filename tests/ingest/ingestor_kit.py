"""The broker-free gateway core for the ingest tests: an Ingestor on the shared manual clock,
publishing into memory with no retry delay, and the acks its callbacks give."""

from __future__ import annotations

import pytest

from mapservice.ingest.gateway import Ingestor
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher


class Acks:
    """Counts ack() calls, the way paho's client.ack(mid, qos) would be called."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def for_(self, name: str):
        return lambda: self.calls.append(name)


@pytest.fixture
def publisher() -> MemoryPublisher:
    return MemoryPublisher()


@pytest.fixture
def settings() -> Settings:
    return Settings()


@pytest.fixture
def ingestor(settings, publisher, clock) -> Ingestor:
    return Ingestor(settings, publisher, clock, gateway_id="gw-test", retry_delay_s=0)


@pytest.fixture
def acks() -> Acks:
    return Acks()


@pytest.fixture
def gateway():
    """An MqttGateway whose Kafka is nowhere (127.0.0.1:1), closed afterwards: a gateway left
    open keeps its librdkafka clients dialling that address, logging each failure, until
    the test process exits."""
    from mapservice.ingest.gateway import MqttGateway

    made = MqttGateway(Settings(kafka_bootstrap="127.0.0.1:1"))
    yield made
    made.close()
