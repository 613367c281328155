"""The channels of one Foxglove SDK context (`foxglove.Context`): one per topic, made on its
first message, protobuf (Foxglove's own schemas, the MCAP export's) or JSON (with the JSON
schema of mcap_channels.JSON_SCHEMAS), as the MCAP export registers them.

Thread-safe: the live feed's worker and the SDK's callbacks both log."""

from __future__ import annotations

import json
import threading
from typing import Any

import foxglove
from mcap_protobuf.schema import build_file_descriptor_set

from mapservice.adapters.mcap_channels import JSON_SCHEMAS

_NS_PER_MS = 1_000_000


class FoxgloveChannels:
    """Logs messages on the topics of one context, each topic's channel made once."""

    def __init__(self, context: foxglove.Context) -> None:
        self.context = context
        self._channels: dict[str, foxglove.Channel] = {}
        self._lock = threading.Lock()

    def _channel(self, topic: str, schema: foxglove.Schema, encoding: str) -> foxglove.Channel:
        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                channel = self._channels[topic] = foxglove.Channel(
                    topic, schema=schema, message_encoding=encoding, context=self.context
                )
            return channel

    def declare_protobuf(self, topic: str, message_class: Any) -> foxglove.Channel:
        """The topic's channel, of a message class of foxglove_schemas_protobuf (its full name
        is the schema's name), advertised from now on."""
        channel = self._channels.get(topic)
        if channel is None:
            schema = foxglove.Schema(
                name=message_class.DESCRIPTOR.full_name,
                encoding="protobuf",
                data=build_file_descriptor_set(message_class).SerializeToString(),
            )
            channel = self._channel(topic, schema, "protobuf")
        return channel

    def declare_json(self, topic: str, schema_name: str) -> foxglove.Channel:
        """The topic's JSON channel (its schema: mcap_channels.JSON_SCHEMAS), advertised."""
        channel = self._channels.get(topic)
        if channel is None:
            schema = foxglove.Schema(
                name=schema_name,
                encoding="jsonschema",
                data=json.dumps(JSON_SCHEMAS[schema_name]).encode(),
            )
            channel = self._channel(topic, schema, "json")
        return channel

    def listened(self, topic: str) -> bool:
        """Whether a client (or another sink) takes the declared topic's messages now: the
        SDK drops a message nobody takes, so a server without clients need not build it."""
        channel = self._channels.get(topic)
        return channel is not None and channel.has_sinks()

    def any_listened(self) -> bool:
        """Whether a client takes any channel's messages now (none connected: nothing)."""
        return any(channel.has_sinks() for channel in list(self._channels.values()))

    def protobuf(self, topic: str, message: Any, ts_ms: int) -> None:
        channel = self.declare_protobuf(topic, type(message))
        channel.log(message.SerializeToString(), log_time=ts_ms * _NS_PER_MS)

    def json(self, topic: str, schema_name: str, doc: dict[str, Any], ts_ms: int) -> None:
        channel = self.declare_json(topic, schema_name)
        channel.log(json.dumps(doc, separators=(",", ":")).encode(), log_time=ts_ms * _NS_PER_MS)

    def topics(self) -> list[str]:
        with self._lock:
            return sorted(self._channels)

    def close(self) -> None:
        with self._lock:
            for channel in self._channels.values():
                channel.close()
            self._channels.clear()
