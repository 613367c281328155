"""Tells the plant's systems of every incident once its finding is stored (when it begins,
changes severity, ends or is retracted: mapservice/core/incident_alerts.py): on MQTT, one
topic per kind (`<incident_alert_topic_root><kind>`, QoS 1), and to the webhooks operators
registered (webhook_delivery.py). Runs on the store thread right after the findings' insert
returned, and only hands the alerts over: the MQTT client's thread (advertising.py) and the
webhooks' workers send them, so neither a broker nor a receiver can hold the store up.

Which replica sends: the one that stores the findings, i.e. the owner of the partitions
whose poses made them (each replica finds the incidents of the robots it stores). So each
finding is sent once, by one process, and again only where it is found again: after a
rebalance or restart the views are rebuilt from the store and what was stored is known
(`seed`), so only findings that differ from the stored ones are sent.

Retained: the last alert of each kind. A system that subscribes (or reconnects) learns at
once the newest finding of every kind and when it was found, so it can tell a quiet floor
from a dead feed; what is open now is what `GET /api/v1/incidents` lists. Not one retained
message per incident: nothing would ever clear those of incidents long ended, and the
broker would keep them all. A retraction is an alert of its own (`event: retracted`), and
it replaces the retained one like any other.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import structlog
from prometheus_client import Counter

from mapservice.core.incident_alerts import AlertLedger, alert_document, alert_topic
from mapservice.core.incident_model import Incident

from .advertising import AdvertisementQueue
from .webhook_delivery import WebhookDeliveries

log = structlog.get_logger(__name__)

ALERTS = Counter(
    "mapservice_incident_alerts_total", "Incident alerts handed over to be sent", ["event"]
)


class IncidentAlerts:
    def __init__(
        self,
        topic_root: str,
        mqtt: AdvertisementQueue | None,
        webhooks: WebhookDeliveries | None,
    ) -> None:
        self.topic_root, self.mqtt, self.webhooks = topic_root, mqtt, webhooks
        self.ledger = AlertLedger()

    def seed(self, stored: Iterable[Incident]) -> None:
        """The incidents stored when the views were rebuilt: found again unchanged, they
        are not announced; changed, they are not `new`."""
        self.ledger.seed(stored)

    def announce(
        self, found: Sequence[Incident], retracted: Sequence[Incident], found_ms: int
    ) -> None:
        """The findings just stored: each an alert on its kind's topic and to the webhooks."""
        for event, incident in self.ledger.classify(found, retracted):
            doc = alert_document(incident, event, found_ms)
            try:
                if self.mqtt is not None:
                    topic = alert_topic(self.topic_root, incident.kind)
                    self.mqtt.to_topic(topic, doc, retain=True)
                if self.webhooks is not None:
                    self.webhooks.offer(doc)
            except Exception as exc:  # the findings are stored: an alert never undoes that
                log.warning("incident alert not handed over", error=str(exc), kind=incident.kind)
                continue
            ALERTS.labels(event).inc()

    def keep(self, held: Iterable[str], held_count: int) -> None:
        """Lets go of incidents the detection no longer holds, once they are many."""
        if len(self.ledger) > 2 * held_count + 1000:
            self.ledger.keep(held)
