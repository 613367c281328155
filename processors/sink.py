"""Pure part of the history sink: raw Kafka values to what the store appends."""

from __future__ import annotations

from collections.abc import Iterable

import msgspec

from mapservice.events import DeadLetter, Envelope, decode, decode_dead_letter


def split_events(values: Iterable[bytes], now_ms: int) -> tuple[list[Envelope], list[DeadLetter]]:
    """Decodes envelopes; a record that is not one becomes a dead letter, not a crash."""
    events: list[Envelope] = []
    bad: list[DeadLetter] = []
    for value in values:
        try:
            events.append(decode(value))
        except (msgspec.DecodeError, TypeError, UnicodeDecodeError) as exc:
            bad.append(DeadLetter(reason="undecodable_event", detail=str(exc)[:500],
                                  mqtt_topic="", payload=value or b"", receive_time_ms=now_ms,
                                  gateway="processors"))
    return events, bad


def decode_dead_letters(values: Iterable[bytes], now_ms: int) -> list[DeadLetter]:
    out = []
    for value in values:
        try:
            out.append(decode_dead_letter(value))
        except (msgspec.DecodeError, TypeError, UnicodeDecodeError) as exc:
            out.append(DeadLetter(reason="undecodable_dead_letter", detail=str(exc)[:500],
                                  mqtt_topic="", payload=value or b"", receive_time_ms=now_ms,
                                  gateway="processors"))
    return out
