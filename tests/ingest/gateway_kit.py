"""The gateway's command half for the ingest tests, wired as the gateway wires it: its
Ingestor (robots' answers in) and its CommandRelay (operators' commands out, to 2019 robots
and VDA 5050 vehicles) on one manual clock, with an in-memory publisher."""

from __future__ import annotations

import json

from mapservice.adapters.clock import ManualClock
from mapservice.core.commands import CommandIssued
from mapservice.core.events import decode, encode, make_envelope
from mapservice.ingest.command_relay import CommandRelay
from mapservice.ingest.gateway import Ingestor
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher

NOW = 1_795_255_200_000


class Gateway:
    """What the relay delivers is kept in `sent` as (MQTT topic, the JSON message decoded)."""

    def __init__(self) -> None:
        self.settings = Settings()
        self.publisher = MemoryPublisher()
        self.clock = ManualClock(NOW)
        self.ingestor = Ingestor(self.settings, self.publisher, self.clock, gateway_id="gw")
        self.sent: list[tuple[str, dict]] = []
        router = self.ingestor.router
        self.relay = CommandRelay(
            self.settings,
            lambda t, p: self.sent.append((t, json.loads(p))),
            self.clock.now_ms,
            router.commands,
            router.vda_commands,
        )

    def issue(self, cid: str, robot: str, kind: str = "pause", at_ms: int = NOW) -> bool:
        """An operator's command read from the command topic; True when it was delivered."""
        command = CommandIssued(cid, robot, kind, "operator:ab12", at_ms)
        return self.relay.handle(encode(make_envelope(robot, at_ms, at_ms, command)))

    def command_events(self) -> list:
        """The payloads published to the command topic so far (acks and outcomes)."""
        self.publisher.flush()
        return [
            decode(v).payload for _, v in self.publisher.records[self.settings.topic_command_events]
        ]
