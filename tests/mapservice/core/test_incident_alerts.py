"""An incident alert is the incident as the API lists it plus what happened to it: every
kind's document reads back through the API's own model, and the ledger calls each finding of
a random sequence new, changed, ended or retracted as a receiver keeping its own record
needs it."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.api.routers.incidents import Incident as ListedIncident
from mapservice.core.incident_alerts import ALERT_EVENTS, AlertLedger, alert_document, alert_topic
from mapservice.core.incident_model import KINDS, SEVERITIES, Incident, PoseRef, incident_id


def incident(kind: str, start_ms: int, ongoing: bool, end_ms: int | None = None) -> Incident:
    robots = ("a", "b") if kind == "near_miss" else ("a",)
    end = start_ms + 5_000 if end_ms is None else end_ms
    return Incident(
        incident_id=incident_id(kind, robots, start_ms),
        kind=kind,
        robots=robots,
        start_ms=start_ms,
        end_ms=end,
        ongoing=ongoing,
        x=1.5,
        y=-2.0,
        severity=SEVERITIES[0],
        measure=0.4,
        evidence=(PoseRef("a", start_ms, 1.5, -2.0), PoseRef(robots[-1], end, 1.6, -2.0)),
    )


@pytest.mark.parametrize("event", ALERT_EVENTS)
@pytest.mark.parametrize("kind", KINDS)
def test_every_kinds_alert_is_the_listed_incident_with_its_event(kind: str, event: str) -> None:
    found = incident(kind, 1_000, ongoing=True)
    doc = alert_document(found, event, 9_000)
    listed = ListedIncident.model_validate(doc).model_dump()
    assert {k: doc[k] for k in listed} == listed
    assert set(doc) - set(listed) == {"event", "found_ms"}
    assert doc["event"] == event and doc["found_ms"] == 9_000
    assert doc["ongoing"] is (event != "retracted")  # a retracted incident is no longer open
    assert alert_topic("iot/incidents/", kind) == alert_topic("iot/incidents", kind)
    assert alert_topic("iot/incidents/", kind) == f"iot/incidents/{kind}"


def test_an_unknown_event_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown alert event"):
        alert_document(incident("stuck", 0, True), "opened", 0)


# A sequence of findings: (incident number, ongoing?, retracted?)
steps = st.lists(st.tuples(st.integers(0, 4), st.booleans(), st.booleans()), max_size=40)


@given(steps, st.sets(st.integers(0, 4)))
def test_the_ledger_names_each_finding_as_a_receivers_record_needs(steps, stored) -> None:
    """A receiver that opens on `new`, updates on `changed`, closes on `ended` and drops on
    `retracted` holds exactly the incidents last found, each as last found; one the ledger
    was seeded with (stored before a restart) is never announced as new."""
    ledger = AlertLedger()
    ledger.seed(incident("stuck", n * 1000, ongoing=True) for n in stored)
    record: dict[str, bool] = {f"stuck-{n}": True for n in stored}  # the receiver's, by id
    expected = dict(record)
    for n, ongoing, retract in steps:
        i = incident("stuck", n * 1000, ongoing)
        key = f"stuck-{n}"
        if retract:
            ((event, _),) = ledger.classify([], [i])
            assert event == "retracted"
            record.pop(key, None)
            expected.pop(key, None)
            continue
        ((event, _),) = ledger.classify([i], [])
        if key not in record:
            assert event == "new"
        elif record[key] and not ongoing:
            assert event == "ended"
        else:
            assert event == "changed"
        record[key] = ongoing
        expected[key] = ongoing
    assert record == expected


def test_the_ledger_forgets_what_the_detection_let_go_of() -> None:
    ledger = AlertLedger()
    a, b = incident("offline", 0, True), incident("offline", 1000, True)
    ledger.classify([a, b], [])
    ledger.keep([b.incident_id])
    assert [e for e, _ in ledger.classify([a, b], [])] == ["new", "changed"]
