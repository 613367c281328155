"""Pure routing: an MQTT message becomes a Kafka record (event or dead letter)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

from mapservice.core.commands import COMMAND_EVENTS
from mapservice.core.events import (
    ChunkUpdated,
    DeadLetter,
    Envelope,
    PoseReported,
    VdaConnectionReported,
    VdaFactsheetReported,
    VdaStateReported,
    encode,
    encode_dead_letter,
    kafka_key,
    make_envelope,
)
from mapservice.core.intake import Intake
from mapservice.core.wire2019 import Reason, Rejection
from mapservice.settings import Settings

from .command_relay import CommandBook
from .command_responses import decode_response
from .vda5050 import VdaIngest
from .vda_commands import VdaCommands

# Kafka's default record limit is 1 MB; a dead letter keeps at most this much of a message.
DEAD_LETTER_PAYLOAD_MAX = 64 * 1024


@dataclass(frozen=True)
class Record:
    topic: str
    key: bytes
    value: bytes
    reason: str | None  # None for an accepted event
    envelope: Envelope | None = None
    # Further events the message made (a VDA state's answers to commands), published too.
    extra: tuple[Record, ...] = ()


def _prefix(topic_filter: str) -> str:
    """The topic prefix a one-robot-per-level filter stands for: "a/b/#" or "a/b/+" -> "a/b/"."""
    return (
        topic_filter[:-1] if topic_filter.endswith(("#", "+")) else topic_filter.rstrip("/") + "/"
    )


class Router:
    """Knows the configured MQTT topics and the Kafka topics they feed."""

    def __init__(
        self, settings: Settings, gateway_id: str, commands: CommandBook | None = None
    ) -> None:
        self.settings = settings
        self.gateway_id = gateway_id
        self.chunk_topic = settings.create_chunk_topic or None  # empty: not taken
        # "iot/coordinates/#" or ".../+" -> "iot/coordinates/"; robots publish on
        # iot/coordinates/<id>.
        self.coordinate_prefix = _prefix(settings.coordinate_topic)
        # "iot/chunks/create/+" -> "iot/chunks/create/": a robot's own chunk topic, which
        # names it as the coordinate topic does (the broker's ACL ties it to the username).
        self.robot_chunk_prefix = (
            _prefix(settings.robot_chunk_topic) if settings.robot_chunk_topic else None
        )
        self.vda = VdaIngest(settings.vda5050_interface, settings.vda5050_map_transforms)
        # "iot/robots/" + <robotId> + "/command-events": a robot's answers to its commands,
        # judged against the commands the gateway delivered (`commands`, the relay's book).
        self.robot_root = (
            settings.robot_topic_root.rstrip("/") + "/" if settings.robot_topic_root else None
        )
        self.commands = commands or CommandBook()
        self.vda_commands = VdaCommands(settings.vda5050_interface, self.commands.robot_of)

    def _command_robot(self, mqtt_topic: str) -> str | None:
        """The robot of a `<root><robotId>/command-events` topic, else None."""
        if not self.robot_root or not mqtt_topic.startswith(self.robot_root):
            return None
        robot_id, _, rest = mqtt_topic[len(self.robot_root) :].partition("/")
        return robot_id if rest == "command-events" and robot_id else None

    def route(self, mqtt_topic: str, payload: bytes, receive_ms: int, intake: Intake) -> Record:
        """The record for one message; its 2019 writes pass `intake` (the limits of now)."""
        limits = intake.limits
        try:
            if mqtt_topic == self.chunk_topic:
                result = intake.chunk(payload, receive_ms)
            elif (
                self.robot_chunk_prefix
                and mqtt_topic.startswith(self.robot_chunk_prefix)
                and "/" not in mqtt_topic[len(self.robot_chunk_prefix) :]
            ):  # one level: `+`
                robot_id = mqtt_topic[len(self.robot_chunk_prefix) :]
                result = intake.chunk(payload, receive_ms, topic_robot_id=robot_id)
            elif self.vda.handles(mqtt_topic):
                result, msg = self.vda.decode_message(mqtt_topic, payload, receive_ms, limits)
                if not isinstance(result, Rejection):
                    return self._vda_record(mqtt_topic, msg or {}, result, receive_ms)
            elif (answering := self._command_robot(mqtt_topic)) is not None:
                answer = decode_response(
                    payload, answering, receive_ms, limits, self.commands.robot_of
                )
                result = (
                    answer
                    if isinstance(answer, Rejection)
                    else make_envelope(answering, answer[0], receive_ms, answer[1])
                )
            elif mqtt_topic.startswith(self.coordinate_prefix):
                robot_id = mqtt_topic[len(self.coordinate_prefix) :]
                result = intake.coordinates(robot_id, payload, receive_ms)
            else:
                result = Rejection(
                    Reason.UNKNOWN_TOPIC, f"no handler for MQTT topic {mqtt_topic[:200]!r}"
                )
            if isinstance(result, Rejection):
                return self.dead_letter(
                    mqtt_topic, payload, receive_ms, result.reason, result.detail
                )
            return Record(self.topic_for(result), kafka_key(result), encode(result), None, result)
        except Exception as exc:  # noqa: BLE001 - no message may stop the gateway
            return self.dead_letter(
                mqtt_topic,
                payload,
                receive_ms,
                Reason.INTERNAL_ERROR,
                f"{type(exc).__name__}: {str(exc)[:500]}",
            )

    def _vda_record(
        self, mqtt_topic: str, msg: dict[str, Any], envelope: Envelope, receive_ms: int
    ) -> Record:
        """A vehicle's event; its version is remembered (its commands are sent in it) and
        a `state`'s actionStates naming commands become those commands' answers."""
        event = envelope.payload
        if isinstance(event, (VdaStateReported, VdaConnectionReported, VdaFactsheetReported)):
            self.vda_commands.heard(envelope.robot_id, event.vda_version)
        extra: list[Record] = []
        if mqtt_topic.endswith("/state"):
            # 3.0 reports instant actions apart from the order's actions.
            states = [*msg.get("actionStates", ()), *msg.get("instantActionStates", ())]
            for answer in self.vda_commands.answers(envelope.robot_id, states):
                made = make_envelope(envelope.robot_id, envelope.event_time_ms, receive_ms, answer)
                extra.append(
                    Record(self.topic_for(made), kafka_key(made), encode(made), None, made)
                )
        return Record(
            self.topic_for(envelope),
            kafka_key(envelope),
            encode(envelope),
            None,
            envelope,
            tuple(extra),
        )

    def dead_letter(
        self, mqtt_topic: str, payload: bytes, receive_ms: int, reason: Reason, detail: str
    ) -> Record:
        """The dead-letter record for a message: its bytes as they came, or, beyond
        DEAD_LETTER_PAYLOAD_MAX, their start with the size and a hash of the whole (a
        dead letter must itself fit in a Kafka record)."""
        if len(payload) > DEAD_LETTER_PAYLOAD_MAX:
            digest = hashlib.sha256(payload).hexdigest()
            detail = (
                f"{detail} (payload truncated to its first {DEAD_LETTER_PAYLOAD_MAX} of "
                f"{len(payload)} bytes; sha256 of the whole: {digest})"
            )
            payload = payload[:DEAD_LETTER_PAYLOAD_MAX]
        letter = DeadLetter(
            reason=reason.value,
            detail=detail[:2000],
            mqtt_topic=mqtt_topic[:500],
            payload=payload,
            receive_time_ms=receive_ms,
            gateway=self.gateway_id,
        )
        return Record(
            self.settings.topic_dead_letter,
            mqtt_topic[:500].encode(),
            encode_dead_letter(letter),
            reason.value,
        )

    def topic_for(self, envelope: Envelope) -> str:
        if isinstance(envelope.payload, (PoseReported, VdaStateReported)):
            return self.settings.topic_pose_events
        if isinstance(envelope.payload, ChunkUpdated):
            return self.settings.topic_chunk_events
        if isinstance(envelope.payload, COMMAND_EVENTS):
            return self.settings.topic_command_events
        return self.settings.topic_meta_events
