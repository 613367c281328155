"""Writes from the API go where MQTT writes go: an event on Kafka, stored by the processors.

A request is answered only once Kafka confirmed the record (as the gateway acknowledges
MQTT only then), so a 200 means the event is durable and will be stored.
"""

from __future__ import annotations

import threading
import time

from fastapi import HTTPException

from mapservice.core.annotations import ANNOTATION_EVENTS
from mapservice.core.commands import COMMAND_EVENTS
from mapservice.core.events import ChunkUpdated, Envelope, MapMetaSet, encode, kafka_key
from mapservice.core.ports import EventPublisher
from mapservice.settings import Settings

PUBLISH_TIMEOUT_S = 10.0


def topic_for(settings: Settings, envelope: Envelope) -> str:
    if isinstance(envelope.payload, ChunkUpdated):
        return settings.topic_chunk_events
    if isinstance(envelope.payload, MapMetaSet):
        return settings.topic_meta_events
    if isinstance(envelope.payload, ANNOTATION_EVENTS):
        return settings.topic_annotation_events
    if isinstance(envelope.payload, COMMAND_EVENTS):
        return settings.topic_command_events
    return settings.topic_pose_events


def publish_and_wait(
    publisher: EventPublisher,
    settings: Settings,
    envelope: Envelope,
    timeout_s: float = PUBLISH_TIMEOUT_S,
) -> None:
    """Publishes the event and waits for Kafka's confirmation; a 503 if it does not come."""
    done = threading.Event()
    errors: list[Exception] = []

    def on_done(error: Exception | None) -> None:
        if error is not None:
            errors.append(error)
        done.set()

    publisher.publish(topic_for(settings, envelope), kafka_key(envelope), encode(envelope), on_done)
    deadline = time.monotonic() + timeout_s
    while not done.is_set() and time.monotonic() < deadline:
        publisher.poll(0.05)  # serves delivery callbacks (ours or another request's)
    if errors or not done.is_set():
        reason = str(errors[0]) if errors else f"no confirmation within {timeout_s:.0f} s"
        raise HTTPException(
            503,
            f"the event log (Kafka) did not take the write: {reason}; "
            "nothing was stored, retry later",
        )
