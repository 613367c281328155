"""Every incident finding the processors store is announced once it is stored, and only
then: on `iot/incidents/<kind>` (retained) and to the webhooks, new, changed, ended or
retracted; a failed insert announces nothing until its retry stores it, and a restart does
not announce again what was stored before it."""

from __future__ import annotations

import asyncio

from mapservice.core.annotations import AnnotationCreated, Zone
from mapservice.core.events import encode, make_envelope
from mapservice.core.incident_model import KINDS
from tests.conftest import chunk_event, meta_event
from tests.mapservice.core.event_history import ack, issue, vda_state
from tests.processors.history_consumer_kit import NOW, POSES, live_views
from tests.processors.test_incident_watch import PATH, Floor, IncidentLog

T0 = NOW - 120_000
PIT = Zone("pit", "keep_out", ((19.0, 19.0), (21.0, 19.0), (21.0, 21.0), (19.0, 21.0)))


def every_kind(floor: Floor, ev) -> None:
    """A minute of a floor where every kind of incident happens: s stands still with a
    path for 40 s; a passes b at 0.5 m; c's battery runs low in a keep-out zone; b writes a
    chunk a wrote otherwise; a refuses a command; vehicle v reports a fatal error."""
    before = [
        meta_event(T0 - 10_000),  # the map the zone's pixels are on: (-1.5, 2.0) to (23.5, 22)
        make_envelope("operator:ab12", T0 - 5000, T0 - 5000, AnnotationCreated("pit", "op", PIT)),
    ]
    at = {
        2: [issue("a", T0 + 2000, "go"), chunk_event("a", T0 + 2000, pixels=bytes(10_000))],
        3: [
            ack("a", T0 + 3000, "go", "rejected"),
            chunk_event("b", T0 + 3000, pixels=bytes([7]) * 10_000),
        ],
        5: [vda_state("v", T0 + 5000, [("FATAL", "lift")])],
    }
    for e in before:
        floor.source.append(POSES, encode(e))
    for t in range(60):
        for e in at.get(t, []):
            floor.source.append(POSES, encode(e))
        floor.send(
            ev,
            ("s", t, 5.0 if t < 40 else 5.0 + t - 40, 5.0, 80.0, PATH),
            ("a", t, float(t) * 0.5, 3.0, 80.0, PATH),
            ("b", t, 15.0, 3.5, 80.0, None),
            ("c", t, 20.0, 20.0, 20.0 - t * 0.25, None),
        )


class Captured:
    """An MQTT advertiser that keeps what it was handed (and whether it was stored then)."""

    def __init__(self, store: IncidentLog) -> None:
        self.store = store
        self.sent: list[tuple[str, dict, bool, set[str]]] = []

    def start(self) -> None:
        pass

    def publish(self, payload: dict) -> bool:
        return self.publish_to("chunks", payload)

    def publish_to(self, topic: str, payload: dict, retain: bool = False) -> bool:
        stored = {i.incident_id for i in self.store.incidents(0, 2**62)}
        self.sent.append((topic, payload, retain, stored))
        return True

    def stop(self) -> None:
        pass


class AlertFloor(Floor):
    def start(self) -> None:
        super().start()
        self.mqtt = getattr(self, "mqtt", None) or Captured(self.store)
        views = live_views(
            self.views.settings,
            self.store,
            self.mqtt,
            self.consumer.sink.thread,
            now_ms=lambda: self.now,
        )
        views.load()
        self.views = self.consumer.views = views

    def alerts(self) -> list[dict]:
        self.views.flush()
        return [doc for topic, doc, _, _ in self.mqtt.sent if topic.startswith("iot/incidents/")]


def test_every_stored_finding_is_announced_on_its_kinds_topic_after_it_is_stored(ev) -> None:
    floor = AlertFloor()
    every_kind(floor, ev)
    floor.tick(11)  # everyone falls silent
    alerts = floor.alerts()
    assert {a["kind"] for a in alerts} == set(KINDS)
    for topic, doc, retain, stored in floor.mqtt.sent:
        if topic.startswith("iot/incidents/"):
            assert topic == f"iot/incidents/{doc['kind']}" and retain
            assert doc["id"] in stored  # published only once the finding was stored
    # every stored incident was announced; the last alert of one that ended is as it is
    # stored, of one going on says so with its severity (not every refinement is alerted)
    last = {a["id"]: a for a in alerts}
    stored = floor.stored()
    assert {i.incident_id for i in stored} <= set(last)
    for i in stored:
        doc = last[i.incident_id]
        assert (doc["ongoing"], doc["severity"]) == (i.ongoing, i.severity)
        if not i.ongoing:
            assert (doc["end_ms"], doc["measure"]) == (i.end_ms, i.measure)
    # each incident's first alert is `new`; the stuck run ended when s drove off
    first: dict[str, str] = {}
    for a in alerts:
        first.setdefault(a["id"], a["event"])
    assert set(first.values()) == {"new"}
    stuck = [a["event"] for a in alerts if a["kind"] == "stuck"]
    assert stuck[0] == "new" and "ended" in stuck


def test_a_retraction_is_announced(ev) -> None:
    floor = AlertFloor()
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(10)])
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(25, 35)])
    (silence,) = floor.alerts()
    assert (silence["kind"], silence["event"]) == ("offline", "new")
    floor.send(ev, *[("r", t, float(t), 0.0, 80.0, None) for t in range(10, 25, 2)])
    assert floor.stored() == []
    retraction = floor.alerts()[-1]
    assert (retraction["id"], retraction["event"], retraction["ongoing"]) == (
        silence["id"],
        "retracted",
        False,
    )


def test_a_failed_insert_announces_nothing_and_a_restart_nothing_again(ev) -> None:
    store = IncidentLog(failures=1)
    floor = AlertFloor(store)
    floor.send(ev, *[("s", t, 3.0, 3.0, 5.0, PATH) for t in range(40)])
    alerts = floor.alerts()
    assert sorted(a["kind"] for a in alerts if a["event"] == "new") == ["battery_low", "stuck"]
    assert all(stored for _, _, _, stored in floor.mqtt.sent)
    floor.start()  # a restart: the views rebuilt from the store
    asyncio.run(floor.views.write_found_until_done())
    floor.send(ev, ("s", 40, 3.0, 3.0, 5.0, PATH))
    assert floor.alerts()[len(alerts) :] == []  # stuck a second longer: no alert
    floor.send(ev, ("s", 41, 9.0, 3.0, 5.0, PATH))  # drives off
    later = floor.alerts()[len(alerts) :]
    assert [(a["kind"], a["event"]) for a in later] == [("stuck", "ended")]


def test_an_alert_that_cannot_be_handed_over_does_not_fail_the_stored_findings(ev) -> None:
    """On shutdown the MQTT queue closes before the consumer's last write: the findings are
    stored all the same, their alerts logged as not sent."""
    floor = AlertFloor()
    floor.views.close()  # the queue's thread is gone
    writes = floor.views.incidents.writer
    floor.send(ev, *[("s", t, 3.0, 3.0, 5.0, PATH) for t in range(40)])
    assert sorted(i.kind for i in writes.incidents(0, floor.now + 1)) == ["battery_low", "stuck"]
    assert [topic for topic, *_ in floor.mqtt.sent if topic.startswith("iot/incidents/")] == []
