"""What the plant's systems are told of each incident finding: the alert's document (the
same fields as `GET /api/v1/incidents` lists, plus what happened to the incident), its MQTT
topic, and which of new / changed / ended / retracted a finding is.

An alert goes out when an incident begins, when its severity changes while it goes on (a
near miss comes within half the distance, a robot stuck for five minutes: a receiver
escalates), when it ends (with its final figures and evidence) and when a late pose breaks
it (retracted). Not for what is refined in between: a near miss's closest distance dropping
by a few centimetres, a stuck run's growing length, which the store and the live page get;
a receiver pages people on alerts, and two robots passing each other would otherwise send
one a batch. An alert says which, so a receiver can open, update and close its own record
of the incident keyed by `id`, and drop it on a retraction.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from mapservice.core.incident_model import Incident

# What happened to the incident, as of this finding.
ALERT_EVENTS = ("new", "changed", "ended", "retracted")


def alert_topic(root: str, kind: str) -> str:
    """`<root><kind>`, e.g. iot/incidents/near_miss."""
    return f"{root.rstrip('/')}/{kind}"


def alert_document(incident: Incident, event: str, found_ms: int) -> dict[str, Any]:
    """The alert's JSON document: the incident as the API lists it, `event` and when it
    was found (`found_ms`, the processors' clock)."""
    if event not in ALERT_EVENTS:
        raise ValueError(f"unknown alert event {event!r}")
    return {
        "event": event,
        "found_ms": found_ms,
        "id": incident.incident_id,
        "kind": incident.kind,
        "robots": list(incident.robots),
        "start_ms": incident.start_ms,
        "end_ms": incident.end_ms,
        "ongoing": incident.ongoing and event != "retracted",
        "x": incident.x,
        "y": incident.y,
        "severity": incident.severity,
        "measure": incident.measure,
        "evidence": [
            {"robotId": e.robot_id, "ts_ms": e.ts_ms, "x": e.x, "y": e.y} for e in incident.evidence
        ],
    }


def _alerted(incident: Incident) -> tuple[bool, str, tuple[str, ...]]:
    """What a finding must differ in from the last alert of its incident to be alerted."""
    return incident.ongoing, incident.severity, incident.robots


class AlertLedger:
    """Which incidents alerts were sent for, and each as it was then: what makes a finding
    `new`, `changed` or `ended`, or not worth an alert. Seeded with the incidents stored
    when the views are rebuilt (a restart does not announce them again as new), and kept
    to the incidents the detection still holds (`keep`): a finding of one forgotten since
    is announced as new, with the same id."""

    def __init__(self) -> None:
        self._sent: dict[str, tuple[bool, str, tuple[str, ...]]] = {}

    def __len__(self) -> int:
        return len(self._sent)

    def seed(self, incidents: Iterable[Incident]) -> None:
        self._sent = {i.incident_id: _alerted(i) for i in incidents}

    def classify(
        self, found: Iterable[Incident], retracted: Iterable[Incident]
    ) -> list[tuple[str, Incident]]:
        """(event, incident) for each finding an alert is due for, and remembers them."""
        out: list[tuple[str, Incident]] = []
        for incident in found:
            now = _alerted(incident)
            was = self._sent.get(incident.incident_id)
            if was == now:
                continue  # refined, or lasted longer
            if was is None:
                event = "new"
            elif was[0] and not incident.ongoing:
                event = "ended"
            else:
                event = "changed"
            self._sent[incident.incident_id] = now
            out.append((event, incident))
        for incident in retracted:
            self._sent.pop(incident.incident_id, None)
            out.append(("retracted", incident))
        return out

    def keep(self, ids: Iterable[str]) -> None:
        """Forgets every incident but these (the ones the detection still holds)."""
        wanted = set(ids)
        self._sent = {k: v for k, v in self._sent.items() if k in wanted}
