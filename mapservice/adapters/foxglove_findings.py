"""What the processors found, on one Foxglove SDK context: the incidents (`/incidents`, their
markers on `/incidents/markers`), the conflicts (`/conflicts`) and each VDA 5050 vehicle's
errors and connection state, with the MCAP export's topics, schemas and messages
(mcap_findings.py). Part of a scene
(foxglove_scene.py), driven by its owner's thread: a seek's picture (the incidents going on
and the errors standing at T), a replay's span, the live stream's incident messages, and
the live re-read of conflicts and VDA 5050 facts (they are not on the live topic).

Keeps the incidents going on and each vehicle's latest errors, so that a client
subscribing later gets them again.

Not thread-safe (see foxglove_scene.py).

May depend on: the ports (through the replay sources)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from mapservice.adapters.foxglove_channels import FoxgloveChannels
from mapservice.adapters.mcap_channels import (
    CONFLICT_SCHEMA_NAME,
    CONFLICTS_TOPIC,
    INCIDENT_MARKERS_TOPIC,
    INCIDENT_SCHEMA_NAME,
    INCIDENTS_TOPIC,
)
from mapservice.adapters.mcap_export import ReplaySources
from mapservice.adapters.mcap_findings import (
    Message,
    conflict_messages,
    incident_doc,
    incident_marker,
    incident_messages,
    incident_of_live,
    incidents_at,
    vda_errors_at,
    vda_messages,
)

# Live: the conflicts and VDA 5050 facts of this long before the last re-read are read
# again (a row stored after its event time's re-read came is sent at the next one).
LATE_MS = 60_000
# Incidents kept going on for a late subscriber: past this many, the oldest are forgotten
# (their end still goes out).
_MAX_GOING_ON = 10_000


class FoxgloveFindings:
    def __init__(self, channels: FoxgloveChannels, sources: ReplaySources) -> None:
        self.channels, self.sources = channels, sources
        self.going_on: dict[str, tuple[int, dict[str, Any]]] = {}  # id -> (time, doc)
        self.latest: dict[str, tuple[int, str, dict[str, Any]]] = {}  # VDA topic -> message
        self.sent = 0  # messages sent (tests, metrics)
        self._read_to: int | None = None  # live: where the last re-read ended
        self._read_keys: set[tuple[int, str, str]] = set()  # what it sent of its span
        self._unheard = False  # live: re-reads were skipped while no client listened
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        channels.declare_json(INCIDENTS_TOPIC, INCIDENT_SCHEMA_NAME)
        channels.declare_protobuf(INCIDENT_MARKERS_TOPIC, SceneUpdate)
        channels.declare_json(CONFLICTS_TOPIC, CONFLICT_SCHEMA_NAME)

    def draw_at(self, at_ms: int) -> None:
        """The incidents going on and each vehicle's errors standing at `at_ms`."""
        self.going_on, self.latest = {}, {}
        self.send(incidents_at(self.sources.incidents, at_ms))
        self.send(vda_errors_at(self.sources.vda, at_ms))
        self._read_to, self._read_keys = at_ms, set()

    def play(self, from_ms: int, to_ms: int) -> list[Message]:
        """[from_ms, to_ms)'s messages in time order (each incident's start and end, the
        conflicts, the VDA 5050 facts), for the caller to send among the poses."""
        out = incident_messages(self.sources.incidents, from_ms, to_ms, going_on=False)
        out += conflict_messages(self.sources.conflicts, from_ms, to_ms)
        out += vda_messages(self.sources.vda, from_ms, to_ms)
        return sorted(out, key=lambda m: m[0])

    def send(self, messages: Iterable[Message]) -> None:
        for ts_ms, topic, schema, doc in messages:
            if topic == INCIDENTS_TOPIC:
                self._keep_incident(ts_ms, doc)
            elif topic != CONFLICTS_TOPIC:
                self.latest[topic] = (ts_ms, schema, doc)
            # Advertised first: a client subscribes to a vehicle's new channel on its
            # advertisement and gets this message then (`resend`).
            self.channels.declare_json(topic, schema)
            if self.channels.listened(topic):
                self.channels.json(topic, schema, doc, ts_ms)
            if topic == INCIDENTS_TOPIC and self.channels.listened(INCIDENT_MARKERS_TOPIC):
                self.channels.protobuf(INCIDENT_MARKERS_TOPIC, incident_marker(doc, ts_ms), ts_ms)
            self.sent += 1

    def _keep_incident(self, ts_ms: int, doc: dict[str, Any]) -> None:
        if doc["event"] in ("end", "retracted"):
            self.going_on.pop(doc["id"], None)
            return
        self.going_on.pop(doc["id"], None)  # its newest message last: the order of age
        self.going_on[doc["id"]] = (ts_ms, doc)
        while len(self.going_on) > _MAX_GOING_ON:
            del self.going_on[next(iter(self.going_on))]

    def live_incident(self, message: Mapping[str, Any]) -> None:
        """A live `incident` message (core/live_incidents.py): its start, an update, its
        end or its retraction."""
        incident = incident_of_live(message["incident"])
        at_ms = int(message["ts_ms"])
        if message["retracted"]:
            event = "retracted"
        elif not incident.ongoing:
            event = "end"
        else:
            event = "update" if incident.incident_id in self.going_on else "start"
        doc = incident_doc(incident, event, max(at_ms, incident.end_ms))
        self.send([(at_ms, INCIDENTS_TOPIC, INCIDENT_SCHEMA_NAME, doc)])

    def reread(self, now_ms: int) -> int:
        """Live: the conflicts and VDA 5050 facts stored since the last re-read (its last
        `LATE_MS` read again, what it sent left out); how many were new.

        While no client listens to any channel nothing is read: a server nobody watches
        cost a quiet plant's processors two store reads every few seconds (a third of the
        Foxglove feed's CPU at 20 robots). The first re-read a client hears again takes each
        vehicle's standing errors first, as a seek does, for its late subscribers."""
        if not self.channels.any_listened():
            self._read_to, self._read_keys, self._unheard = now_ms + 1, set(), True
            return 0
        if self._unheard:
            self._unheard = False
            self.send(vda_errors_at(self.sources.vda, now_ms))
        from_ms = (now_ms if self._read_to is None else self._read_to) - LATE_MS
        read = conflict_messages(self.sources.conflicts, from_ms, now_ms + 1)
        read += vda_messages(self.sources.vda, from_ms, now_ms + 1)
        keys = [(m[0], m[1], repr(m[3])) for m in read]
        fresh = [m for m, k in zip(read, keys, strict=True) if k not in self._read_keys]
        self._read_to, self._read_keys = now_ms + 1, set(keys)
        self.send(sorted(fresh, key=lambda m: m[0]))
        return len(fresh)

    def resend(self, topic: str) -> bool:
        """The topic's current messages again, if it is one of these; whether it was."""
        if topic == INCIDENTS_TOPIC:
            for ts_ms, doc in list(self.going_on.values()):
                self.channels.json(INCIDENTS_TOPIC, INCIDENT_SCHEMA_NAME, doc, ts_ms)
            return True
        if topic == INCIDENT_MARKERS_TOPIC:
            for ts_ms, doc in list(self.going_on.values()):
                self.channels.protobuf(topic, incident_marker(doc, ts_ms), ts_ms)
            return True
        if topic == CONFLICTS_TOPIC:
            return True  # each conflict is an instant's: nothing stands
        kept = self.latest.get(topic)
        if kept is None:
            return False
        ts_ms, schema, doc = kept
        self.channels.json(topic, schema, doc, ts_ms)
        return True
