"""Delivers operators' commands from Kafka to each robot's own MQTT command topic.

The gateway is the component that speaks MQTT to robots both ways, so it delivers their
commands too, and it is where their acks arrive: knowing which command went to which
robot, it refuses an answer from a robot to a command it was not sent (command_responses.py).

Every gateway replica reads the whole command topic (assigned partitions, no consumer
group offsets) from COMMAND_MEMORY_S back, so each knows every recent command whichever
replica a robot's answer reaches. Each replica also delivers what it reads: with N
replicas a robot gets a command N times, as QoS 1 may deliver it twice anyway; robots act
on a command id once. A command older than MAPSERVICE_COMMAND_DELIVERY_TTL_S when read (a
restart, an outage) is remembered but not delivered.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import msgspec
import structlog
from confluent_kafka import OFFSET_END, Consumer, TopicPartition

from mapservice.core.commands import CommandIssued, command_message
from mapservice.core.events import decode
from mapservice.settings import Settings

from .topic_follower import TopicFollower
from .vda_commands import VdaCommandRefused, VdaCommands

log = structlog.get_logger(__name__)

COMMAND_MEMORY_S = 3600  # answers to commands older than this are unknown_command
MAX_REMEMBERED = 200_000  # commands remembered at most (the oldest are forgotten first)
RETRY_S = 2.0  # after a failure, the relay reads again this much later


class CommandBook:
    """Which robot each recent command was sent to (thread-safe, bounded)."""

    def __init__(self, limit: int = MAX_REMEMBERED) -> None:
        self._robots: OrderedDict[str, str] = OrderedDict()
        self._lock = threading.Lock()
        self.limit = limit

    def remember(self, command_id: str, robot_id: str) -> None:
        with self._lock:
            self._robots[command_id] = robot_id
            while len(self._robots) > self.limit:
                self._robots.popitem(last=False)

    def robot_of(self, command_id: str) -> str | None:
        with self._lock:
            return self._robots.get(command_id)


class CommandRelay(TopicFollower):
    """Reads the command topic; remembers each command and delivers the fresh ones with
    `publish(mqtt_topic, payload)` (the gateway's MQTT client, QoS 1)."""

    thread_name = "command-relay"
    group_id = "mapservice-gateway-commands"
    poll_s = 0.2

    def __init__(
        self,
        settings: Settings,
        publish: Callable[[str, bytes], object],
        now_ms: Callable[[], int],
        book: CommandBook | None = None,
        vda: VdaCommands | None = None,
    ) -> None:
        super().__init__(settings, settings.topic_command_events)
        self.vda = vda  # commands to VDA 5050 vehicles go out as their instantActions
        self.publish = publish
        self.now_ms = now_ms
        self.book = book or CommandBook()
        self.delivered = 0
        self.failures = 0  # times the reading failed and started again

    def handle(self, value: bytes) -> bool:
        """One record of the command topic; True when it was delivered to its robot."""
        try:
            envelope = decode(value)
        except (msgspec.DecodeError, msgspec.ValidationError) as exc:
            log.warning("command record undecodable; skipped", error=str(exc)[:200])
            return False
        command = envelope.payload
        if not isinstance(command, CommandIssued):
            return False  # a robot's answer: stored by the processors, nothing to deliver
        self.book.remember(command.command_id, command.robot_id)
        age_ms = self.now_ms() - command.issued_at_ms
        if age_ms > self.settings.command_delivery_ttl_s * 1000:
            log.info(
                "command too old to deliver",
                command_id=command.command_id,
                robot_id=command.robot_id,
                age_s=round(age_ms / 1000, 1),
            )
            return False
        if self.vda is not None and self.vda.is_vehicle(command.robot_id):
            try:
                topic, message = self.vda.delivery(command, self.now_ms())
            except VdaCommandRefused as exc:
                log.warning(
                    "command not delivered to a VDA 5050 vehicle",
                    reason=str(exc),
                    command_id=command.command_id,
                    robot_id=command.robot_id,
                )
                return False
            self.publish(topic, msgspec.json.encode(message))
        else:
            self.publish(
                self.settings.command_topic(command.robot_id),
                msgspec.json.encode(command_message(command)),
            )
        self.delivered += 1
        log.info(
            "command delivered",
            command_id=command.command_id,
            robot_id=command.robot_id,
            kind=command.kind,
            issued_by=command.issued_by,
        )
        return True

    def _run(self) -> None:
        """Reads until stopped; a failure (Kafka away at start, a lost assignment) is
        logged and the reading starts again a little later: deliveries never just stop."""
        while not self._stop.is_set():
            try:
                self._read()
            except Exception:  # noqa: BLE001 - logged; the loop starts reading again
                self.failures += 1
                log.exception(
                    "command relay failed; reading the command topic again shortly",
                    hint="is Kafka reachable at MAPSERVICE_KAFKA_BOOTSTRAP?",
                )
                self._stop.wait(RETRY_S)

    def _start_offsets(self, consumer: Consumer, partitions: list[int]) -> list[TopicPartition]:
        """Each partition from its first record of the last COMMAND_MEMORY_S."""
        since = self.now_ms() - COMMAND_MEMORY_S * 1000
        starts = consumer.offsets_for_times(
            [TopicPartition(self.topic, p, since) for p in partitions], timeout=30
        )
        log.info("command relay reading", topic=self.topic, partitions=len(partitions))
        # No record at or after `since` in a partition: its offset is -1, read from its end.
        return [
            TopicPartition(self.topic, tp.partition, tp.offset if tp.offset >= 0 else OFFSET_END)
            for tp in starts
        ]

    def _on_record(self, value: bytes | None) -> None:
        if value is None:
            return  # a tombstone: nothing to deliver
        try:
            self.handle(value)
        except Exception:  # noqa: BLE001 - one bad record must not stop deliveries
            log.exception("command delivery failed; going on")
