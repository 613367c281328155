"""confluent-kafka idempotent producer behind the EventPublisher port.

A producer can get stuck for good: after a fatal error (librdkafka refuses every later
record), or against a broker that lost its producer state, as a restarted tansu (memory
storage) does: it answers UNKNOWN_PRODUCER_ID to every produce, librdkafka bumps the
epoch locally and tries again, forever, and every record times out. So a record that
times out or fails fatally renews the producer (a new one, a new producer id from the
broker); the old one's records are purged (each reported failed; one that had reached
the broker may end up in Kafka twice, which the history's natural identity folds) and
the caller produces them again, on the new one.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

import structlog
from confluent_kafka import KafkaError, KafkaException, Message, Producer
from prometheus_client import Counter

from mapservice.adapters.kafka_logs import logged
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

RENEWALS = Counter(
    "mapservice_kafka_producer_renewals_total",
    "Kafka producers replaced after a record timed out or a fatal error",
)

# A record not confirmed within this long is reported failed (and produced again by the
# caller); it also bounds how long a stuck producer holds records before it is renewed.
MESSAGE_TIMEOUT_MS = 10_000
# Renewals at most this often: in a long outage every record times out, one renewal is enough.
RENEW_INTERVAL_S = 10.0


def producer_config(
    settings: Settings, client_id: str, message_timeout_ms: int = MESSAGE_TIMEOUT_MS
) -> dict[str, Any]:
    return logged(
        {
            **settings.kafka_config(),
            "client.id": client_id,
            "enable.idempotence": True,
            "acks": "all",
            # 50 ms (the default) batches several events per partition: at 1,000 robots this
            # cut the CPU per event of tansu by ~2/3 and of the gateway by ~1/5; 20 ms doubled
            # tansu's again and took nothing off the end-to-end latency (BENCHMARKS.md).
            "linger.ms": settings.kafka_linger_ms,
            "compression.type": "none",  # aiokafka (faust) lacks lz4 without extras; chunks are zlib already
            # Same partition for the same key as faust/aiokafka producers.
            "partitioner": "murmur2_random",
            "message.timeout.ms": message_timeout_ms,
        }
    )


class RecordTooLarge(ValueError):
    """Kafka refuses a record this large (librdkafka's message.max.bytes)."""


class KafkaPublisher:
    """Created without I/O: librdkafka starts connecting as soon as a Producer exists, so
    the Producer is made on the first publish (an API that never takes a 2019 POST never
    dials Kafka, nor logs that it cannot reach it)."""

    def __init__(
        self,
        settings: Settings,
        client_id: str,
        renew_interval_s: float = RENEW_INTERVAL_S,
        message_timeout_ms: int = MESSAGE_TIMEOUT_MS,
    ) -> None:
        self._config = producer_config(settings, client_id, message_timeout_ms)
        self._producer: Producer | None = None
        self._retiring: list[Producer] = []  # renewed ones: purged, polled until they are empty
        self._purged: set[int] = set()  # ids of retiring producers already purged
        self._error_reports: dict[int, _ErrorReport] = {}  # by id of their producer
        self._renew_interval_s = renew_interval_s
        self._renewed_at = -math.inf
        self._lock = threading.Lock()
        self._closed = False

    @property
    def connected(self) -> bool:
        """Whether a Producer exists yet (it does from the first publish on)."""
        return self._producer is not None

    def _get(self) -> Producer:
        with self._lock:
            if self._closed:
                raise RuntimeError("the Kafka publisher is closed: make a new one to publish")
            if self._producer is None:
                # Without an error_cb, librdkafka's fatal error is raised out of poll().
                report = _ErrorReport(self._on_error)
                producer = report.producer = Producer({**self._config, "error_cb": report})
                self._error_reports[id(producer)] = report
                self._producer = producer
            return self._producer

    def _on_error(self, producer: Producer, err: KafkaError) -> None:
        if _fatal(err):
            self._renew(producer, str(err), at_once=True)

    def _renew(self, stuck: Producer, reason: str, at_once: bool = False) -> None:
        """Replaces `stuck` (if it is still the current producer) by a new one on the next
        publish; not more often than every renew_interval_s unless `at_once` (fatal)."""
        with self._lock:
            now = time.monotonic()
            if self._producer is not stuck or (
                not at_once and now - self._renewed_at < self._renew_interval_s
            ):
                return
            self._retiring.append(stuck)
            self._producer = None
            self._renewed_at = now
        RENEWALS.inc()
        log.warning("kafka producer renewed; failed records are produced again", reason=reason)

    def publish(
        self, topic: str, key: bytes, value: bytes, on_done: Callable[[Exception | None], None]
    ) -> None:
        while True:
            producer = self._get()

            def delivered(
                err: KafkaError | None, _msg: Message, producer: Producer = producer
            ) -> None:
                if err is not None and (_fatal(err) or err.code() == KafkaError._MSG_TIMED_OUT):
                    self._renew(producer, str(err), at_once=_fatal(err))
                on_done(None if err is None else KafkaException(err))

            try:
                producer.produce(topic, value=value, key=key, on_delivery=delivered)
                return
            except BufferError:
                # Local queue full: serve callbacks to make room instead of dropping.
                producer.poll(0.05)
            except KafkaException as exc:
                err = exc.args[0] if exc.args else None
                if err is not None and err.code() == KafkaError.MSG_SIZE_TOO_LARGE:
                    raise RecordTooLarge(f"{len(value)} bytes: larger than Kafka takes") from None
                if err is not None and _fatal(err):
                    self._renew(producer, str(err), at_once=True)  # then produce on the new one
                    continue
                raise

    def _poll_retiring(self) -> None:
        for old in list(self._retiring):
            if id(old) not in self._purged:
                # Here, not in _renew: that may run inside this producer's own callback.
                # A fatal producer would never report what it still holds; a stuck one only
                # after its timeout. Purged, each is reported failed now and produced again.
                self._purged.add(id(old))
                old.purge(in_queue=True, in_flight=True, blocking=False)
            _poll(old, 0)
            if len(old) == 0:  # every delivery report served
                with self._lock:
                    self._retiring.remove(old)
                    self._purged.discard(id(old))
                self._release(old)

    def poll(self, timeout: float) -> None:
        if self._retiring:
            self._poll_retiring()
        producer = self._producer
        if producer is None:
            time.sleep(timeout)  # nothing published yet: nothing to deliver
        elif _poll(producer, timeout) is not None:
            self._renew(producer, "poll raised a fatal error", at_once=True)

    def flush(self, timeout: float) -> int:
        deadline = time.monotonic() + timeout
        left = 0
        for producer in [*self._retiring, self._producer]:
            if producer is not None:
                left += producer.flush(max(0.0, deadline - time.monotonic()))
        self._poll_retiring()
        return left

    def close(self) -> int:
        """Releases every producer without waiting for Kafka (flush first to deliver what is
        held): what they still hold is purged, its delivery reports served (failed), then
        each is closed, so none goes on dialling the brokers. Returns how many records and
        requests were purged. (A producer's own close() flushes: against an unreachable
        broker that would wait for every record's message.timeout.ms.)"""
        with self._lock:
            self._closed = True
            producers = [*self._retiring, *([self._producer] if self._producer else [])]
            self._producer, self._retiring = None, []
            self._purged.clear()
        purged = 0
        for producer in producers:
            purged += len(producer)
            producer.purge(in_queue=True, in_flight=True, blocking=False)
            _poll(producer, 0)
            self._release(producer)
        return purged

    def _release(self, producer: Producer) -> None:
        """Closes a producer that holds nothing any more, now: left to its last reference,
        its threads went on dialling the brokers (the whole outage long, when they are
        gone), as the cycle through its error callback is freed by the cyclic collector
        only, which a process allocating little (a gateway without brokers) seldom runs."""
        report = self._error_reports.pop(id(producer), None)
        if report is not None:
            report.producer = None  # the cycle broken, whatever close() leaves
        producer.close()


class _ErrorReport:
    """A producer's error_cb: passes librdkafka's errors on with the producer they are
    about, until that producer is released."""

    def __init__(self, on_error: Callable[[Producer, KafkaError], None]) -> None:
        self.on_error = on_error
        self.producer: Producer | None = None

    def __call__(self, err: KafkaError) -> None:
        if self.producer is not None:
            self.on_error(self.producer, err)


def _fatal(err: KafkaError) -> bool:
    """A fatal error: this producer accepts nothing any more. (produce() reports it as code
    _FATAL without the fatal flag.)"""
    return err.fatal() or err.code() == KafkaError._FATAL


def _poll(producer: Producer, timeout: float) -> KafkaError | None:
    """Serves delivery reports; returns the fatal error poll() raised, if it did."""
    try:
        producer.poll(timeout)
    except KafkaException as exc:
        err = exc.args[0] if exc.args else None
        if isinstance(err, KafkaError) and _fatal(err):
            log.warning("kafka producer failed fatally", error=str(err))
            return err
        raise
    return None
