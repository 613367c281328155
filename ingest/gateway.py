"""The MQTT-to-Kafka gateway.

Every MQTT message is validated and produced to Kafka (an event, or a dead letter with
its reason), and acknowledged to the MQTT broker only once Kafka confirmed it. The MQTT
session is persistent (clean_session=False, stable client id): if the gateway dies, the
broker keeps and redelivers what was not acknowledged, and the history drops the
duplicates this causes by each event's natural identity.
"""

from __future__ import annotations

import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from functools import partial

import structlog

from mapservice.adapters.clock import clock_from_settings
from mapservice.adapters.kafka_publisher import KafkaPublisher, RecordTooLarge
from mapservice.adapters.mqtt_client import parse_mqtt_url, service_client
from mapservice.core.events import MapMetaSet
from mapservice.core.intake import Intake
from mapservice.core.ports import Clock, EventPublisher
from mapservice.core.wire2019 import Limits, Reason
from mapservice.runtime.health import kafka_check
from mapservice.runtime.health_server import serve_health
from mapservice.runtime.metrics_gate import metrics_gate
from mapservice.settings import Settings

from . import metrics
from .command_relay import CommandRelay
from .meta_watcher import MetaWatcher
from .new_robots import NewRobots
from .router import Record, Router

log = structlog.get_logger(__name__)


RETRY_DELAY_S = 0.2  # a record whose delivery failed is produced again this much later
# The gateway loop's wait for delivery reports: short while failed records wait for their
# retry, else long (a report ends the wait at once).
RETRY_POLL_S = 0.05
IDLE_POLL_S = 0.5
FAILURE_LOG_EVERY_S = 5.0  # in an outage every record fails: one warning per interval


class Ingestor:
    """Broker-free core: route a message, publish it, call `ack` once it is durable.

    A failed delivery is never dropped: the record waits RETRY_DELAY_S in a queue and
    `retry_due()` (the gateway's loop calls it) produces it again; its MQTT ack waits.
    (Sleeping in the delivery callback instead held up every other delivery report: after
    a Kafka outage, a thousand timed-out records took minutes to be retried one by one.)"""

    def __init__(
        self,
        settings: Settings,
        publisher: EventPublisher,
        clock: Clock,
        gateway_id: str,
        retry_delay_s: float = RETRY_DELAY_S,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.router = Router(settings, gateway_id)
        self.publisher = publisher
        self.clock = clock
        self._base_intake = self.intake = Intake.from_settings(settings)
        self.new_robots = NewRobots(settings.ingest_new_robots_limit)
        self._in_flight = 0
        self._lock = threading.Lock()
        self.retry_delay_s = retry_delay_s
        self.monotonic = monotonic
        self._retries: list[tuple[float, Record, object]] = []  # (due, record, done), in order
        self._failures_unlogged = 0
        self._failure_logged_at = -FAILURE_LOG_EVERY_S

    def apply_meta(self, meta: MapMetaSet) -> None:
        self.intake = self._base_intake.with_meta(meta)

    @property
    def limits(self) -> Limits:
        return self.intake.limits

    @property
    def in_flight(self) -> int:
        return self._in_flight

    def handle(self, mqtt_topic: str, payload: bytes, ack: Callable[[], object]) -> Record:
        """Routes, publishes and (once Kafka has the record) acknowledges one message. It
        raises only if even its dead letter cannot be handed to the producer; the message
        is then left unacknowledged, in the broker's session."""
        delivery = _Delivery(self, ack, time.monotonic())
        record = delivery.record = self.router.route(
            mqtt_topic, payload, self.clock.now_ms(), self.intake
        )
        if record.envelope is not None:
            refusal = self.new_robots.refusal(record.envelope.robot_id)
            if refusal is not None:
                record = delivery.record = self.router.dead_letter(
                    mqtt_topic,
                    payload,
                    record.envelope.receive_time_ms,
                    Reason.TOO_MANY_NEW_ROBOTS,
                    refusal,
                )
        if record.reason is not None:
            delivery.outcome = "rejected"
            metrics.REJECTED.labels(record.reason).inc()
            log.info("message rejected", reason=record.reason, mqtt_topic=mqtt_topic[:200])
        for extra in record.extra:
            # Best effort beside the message's own record: retried on a failed delivery
            # like it, but its MQTT ack does not wait for them.
            self.publisher.publish(extra.topic, extra.key, extra.value, _Extra(self, extra))
        with self._lock:
            self._in_flight += 1
        try:
            self._publish(record, delivery)
        except RecordTooLarge as exc:
            # Valid, but too big for a Kafka record: it becomes a dead letter that fits.
            record = delivery.record = self.router.dead_letter(
                mqtt_topic,
                payload,
                record.envelope.receive_time_ms if record.envelope else self.clock.now_ms(),
                Reason.RECORD_TOO_LARGE,
                str(exc),
            )
            delivery.outcome = "rejected"
            metrics.REJECTED.labels(record.reason).inc()
            log.info("message rejected", reason=record.reason, mqtt_topic=mqtt_topic[:200])
            self._publish(record, delivery)
        return record

    def _delivered(self, delivery: _Delivery) -> None:
        delivery.ack()
        with self._lock:
            self._in_flight -= 1
        metrics.OUTCOMES[delivery.outcome].inc()
        metrics.ACK_LATENCY.observe(time.monotonic() - delivery.started)

    def _delivery_failed(self, error: Exception, record: Record, done) -> None:
        metrics.DELIVERY_FAILURES.inc()
        now = self.monotonic()
        with self._lock:
            self._retries.append((now + self.retry_delay_s, record, done))
            self._failures_unlogged += 1
            if now - self._failure_logged_at < FAILURE_LOG_EVERY_S:
                return
            failures, self._failures_unlogged, self._failure_logged_at = (
                self._failures_unlogged,
                0,
                now,
            )
        log.warning(
            "kafka delivery failed, retrying",
            error=str(error),
            topic=record.topic,
            failures=failures,
            waiting=len(self._retries),
        )

    @property
    def retries_waiting(self) -> int:
        return len(self._retries)

    def retry_due(self) -> int:
        """Produces again every failed record whose delay has passed; returns how many."""
        if not self._retries:
            return 0
        now = self.monotonic()
        with self._lock:
            due = [r for r in self._retries if r[0] <= now]
            if not due:
                return 0
            self._retries = [r for r in self._retries if r[0] > now]
        for n, (_, record, done) in enumerate(due):
            try:
                self.publisher.publish(record.topic, record.key, record.value, done)
            except Exception as exc:  # noqa: BLE001 - keep it (and the rest) for the next try
                with self._lock:
                    later = self.monotonic() + self.retry_delay_s
                    self._retries.extend((later, r, d) for _, r, d in due[n:])
                log.warning("producing a failed record again failed", error=str(exc))
                return n
        return len(due)

    def _publish(self, record: Record, done) -> None:
        """Hands the record to the producer; if that fails, the message no longer counts
        as in flight (it was not taken) and the error goes to the caller."""
        try:
            self.publisher.publish(record.topic, record.key, record.value, done)
        except RecordTooLarge:
            raise  # handle() replaces it by a dead letter, still in flight
        except BaseException:
            with self._lock:
                self._in_flight -= 1
            raise


def mqtt_topic(msg) -> str:
    """A paho message's topic. MQTT topics are UTF-8 and brokers refuse others, but paho
    raises on reading one that is not (which would end its network thread): such a topic
    keeps its bytes as escapes behind a prefix no route matches, so the message becomes an
    unknown-topic dead letter instead."""
    try:
        return msg.topic
    except UnicodeDecodeError:
        return "not-utf8:" + msg._topic.decode("utf-8", "backslashreplace")


class _Delivery:
    """The delivery report callback of one message's record: acknowledges the message once
    Kafka has the record, or hands the record back for another try.

    An object rather than a closure: a closure that passes itself on (for the retry) is a
    reference cycle, which only the cyclic garbage collector frees; at thousands of
    messages a second those collections were ~12 % of the gateway's CPU (BENCHMARKS.md).
    """

    __slots__ = ("ack", "ingestor", "outcome", "record", "started")

    def __init__(self, ingestor: Ingestor, ack: Callable[[], object], started: float) -> None:
        self.ingestor = ingestor
        self.ack = ack
        self.started = started
        self.record: Record | None = None
        self.outcome = "accepted"

    def __call__(self, error: Exception | None) -> None:
        if error is not None:
            # Never drop: produce again until Kafka has it (the MQTT ack waits).
            self.ingestor._delivery_failed(error, self.record, self)
            return
        self.ingestor._delivered(self)


class _Extra:
    """The delivery report callback of a further record a message made: produced again
    until Kafka has it."""

    __slots__ = ("ingestor", "record")

    def __init__(self, ingestor: Ingestor, record: Record) -> None:
        self.ingestor = ingestor
        self.record = record

    def __call__(self, error: Exception | None) -> None:
        if error is not None:
            self.ingestor._delivery_failed(error, self.record, self)


class MqttGateway:
    """Wires paho-mqtt (manual acks) to an Ingestor and a Kafka publisher."""

    def __init__(self, settings: Settings, health_port: int | None = None) -> None:
        self.settings = settings
        self.gateway_id = settings.mqtt_client_id
        # Kept apart from `publisher` (which tests may swap): close() releases what was made here.
        self._kafka = KafkaPublisher(settings, client_id=self.gateway_id)
        self.publisher: EventPublisher = self._kafka
        self.ingestor = Ingestor(
            settings, self.publisher, clock_from_settings(settings), self.gateway_id
        )
        self.meta_watcher = MetaWatcher(settings, self.ingestor.apply_meta)
        # Operators' commands, from Kafka to each robot's command topic (QoS 1); the relay's
        # book is what the router judges the robots' answers by.
        self.command_relay = CommandRelay(
            settings,
            self._publish_command,
            self.ingestor.clock.now_ms,
            self.ingestor.router.commands,
            self.ingestor.router.vda_commands,
        )
        self.health_port = health_port
        self.kafka_ready = kafka_check(settings)  # readiness: a broker answers metadata
        self._stop = threading.Event()
        self._connected = threading.Event()
        self.client = None
        # (mid, qos) of messages Kafka has: acknowledged together after each producer poll
        # (its delivery reports come in batches), one wake-up of paho's thread per batch.
        self._acks: deque[tuple[int, int]] = deque()
        # Read when scraped: a gauge moved per message cost a lock each way.
        metrics.IN_FLIGHT.set_function(lambda: self.ingestor.in_flight)

    def _on_connect(self, client, _userdata, _flags, reason_code, _props) -> None:
        if reason_code.is_failure:
            log.error("mqtt connect refused", reason=str(reason_code))
            return
        client.subscribe([(t, 1) for t in self.settings.mqtt_subscriptions])
        self._connected.set()
        metrics.MQTT_CONNECTED.set(1)
        log.info("mqtt connected", subscriptions=self.settings.mqtt_subscriptions)

    def _on_disconnect(self, _client, _userdata, _flags, reason_code, _props) -> None:
        self._connected.clear()
        metrics.MQTT_CONNECTED.set(0)
        if not self._stop.is_set():
            log.warning("mqtt disconnected, reconnecting", reason=str(reason_code))

    def _on_message(self, client, _userdata, msg) -> None:
        if self._stop.is_set():
            return  # not acknowledged: the persistent session redelivers it after restart
        topic = mqtt_topic(msg)
        try:
            self.ingestor.handle(topic, msg.payload, partial(self._acks.append, (msg.mid, msg.qos)))
        except Exception:  # noqa: BLE001 - an exception here would end paho's network thread
            metrics.HANDLING_ERRORS.inc()
            log.exception(
                "message handling failed; left unacknowledged",
                mqtt_topic=topic[:200],
                size=len(msg.payload),
            )

    def _publish_command(self, topic: str, payload: bytes) -> None:
        if self.client is None:
            raise RuntimeError("the gateway's MQTT client is not started yet")
        self.client.publish(topic, payload, qos=1)

    def loop_alive(self) -> bool:
        """Whether paho's network thread runs (it is what receives and acknowledges)."""
        thread = getattr(self.client, "_thread", None)  # paho keeps loop_start()'s thread there
        return thread is not None and thread.is_alive()

    def status(self) -> dict:
        """Liveness: paho's network thread runs (it receives and acknowledges)."""
        alive = self.loop_alive()
        return {
            "ok": alive,
            "mqtt_connected": self._connected.is_set(),
            "mqtt_loop_alive": alive,
            "in_flight": self.ingestor.in_flight,
            "retries_waiting": self.ingestor.retries_waiting,
            "gateway": self.gateway_id,
            "commands_delivered": self.command_relay.delivered,
            "command_relay_failures": self.command_relay.failures,
        }

    def ready(self) -> dict:
        """Readiness: connected to the MQTT broker and a Kafka broker answers metadata."""
        alive, connected, kafka = self.loop_alive(), self._connected.is_set(), self.kafka_ready()
        return {
            "ok": alive and connected and kafka,
            "mqtt_connected": connected,
            "mqtt_loop_alive": alive,
            "kafka": kafka,
            "in_flight": self.ingestor.in_flight,
            "gateway": self.gateway_id,
        }

    def run(self) -> None:
        host, port, _tls = parse_mqtt_url(self.settings.mqtt_url)
        s = self.settings
        self.client = service_client(
            s, self.gateway_id, clean_session=False, manual_ack=True, buffered_reads=True
        )
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = self._on_disconnect
        self.client.on_message = self._on_message
        self.client.reconnect_delay_set(0.2, 5)
        if self.health_port is not None:
            serve_health(s.api_host, self.health_port, self.status, self.ready, metrics_gate(s))
        self.meta_watcher.start()
        log.info("gateway starting", mqtt=f"{host}:{port}", kafka=s.kafka_bootstrap)
        while not self._stop.is_set():
            try:
                self.client.connect(host, port, keepalive=30)
                break
            except OSError as exc:
                log.warning(
                    "mqtt broker unreachable, retrying",
                    error=str(exc),
                    hint=f"is an MQTT broker listening on {host}:{port}?",
                )
                time.sleep(1)
        self.client.loop_start()
        self.command_relay.start()
        try:
            while not self._stop.is_set():
                self._poll()
        finally:
            # New messages are left unacknowledged (the subscription stays in the persistent
            # session); everything already taken is delivered to Kafka and acknowledged.
            remaining = self.publisher.flush(10)
            deadline = time.monotonic() + 2
            while self.ingestor.in_flight and time.monotonic() < deadline:
                self._poll()
            self._send_acks()
            self.client.disconnect()
            self.client.loop_stop()
            self.meta_watcher.stop()
            self.command_relay.stop()
            self.close()
            log.info("gateway stopped", undelivered=remaining)

    def _poll(self) -> None:
        """Serves the producer's delivery reports, acknowledges what they confirmed, and
        produces again what failed and is due."""
        self.publisher.poll(self.poll_timeout())
        self._send_acks()
        self.ingestor.retry_due()

    def poll_timeout(self) -> float:
        """How long the loop may wait for delivery reports. The producer's poll returns as
        soon as one comes, so only a retry falling due needs the short wait; otherwise the
        wait bounds how soon a stop is noticed. (A fixed 50 ms woke a quiet plant's gateway
        20 times a second: a third of its CPU at 20 robots.)"""
        return RETRY_POLL_S if self.ingestor.retries_waiting else IDLE_POLL_S

    def _send_acks(self) -> None:
        acks = []
        while self._acks:
            acks.append(self._acks.popleft())
        if acks:
            self.client.ack_many(acks)

    def stop(self, *_args) -> None:
        self._stop.set()

    def close(self) -> None:
        """Releases the gateway's Kafka clients without waiting for Kafka (run() has flushed
        what it took by then): neither its producer nor its readiness check's admin client
        goes on dialling the brokers."""
        self._kafka.close()
        self.kafka_ready.close()


def run_gateway(settings: Settings, health_port: int | None = None) -> None:
    gateway = MqttGateway(settings, health_port)
    signal.signal(signal.SIGTERM, gateway.stop)
    signal.signal(signal.SIGINT, gateway.stop)
    gateway.run()
