"""An incident alert is the incident as the API lists it plus what happened to it: every
kind's document reads back through the API's own model, and the ledger calls each finding of
a random sequence new, changed, ended or retracted as a receiver keeping its own record
needs it."""

from __future__ import annotations

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.api.routers.incidents import Incident as ListedIncident
from mapservice.core.incident_alerts import ALERT_EVENTS, AlertLedger, alert_document, alert_topic
from mapservice.core.incident_model import (
    KINDS,
    SEVERITIES,
    Incident,
    PoseRef,
    incident_id,
)


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


# A sequence of findings: (incident number, kind, ongoing?, retracted?, end, closest)
steps = st.lists(
    st.tuples(
        st.integers(0, 4),
        st.sampled_from(("stuck", "near_miss")),
        st.booleans(),
        st.booleans(),
        st.integers(5_000, 400_000),
        st.sampled_from((0.3, 0.4, 0.6)),
    ),
    max_size=40,
)


def found_as(kind: str, n: int, ongoing: bool, end_ms: int, closest: float) -> Incident:
    """A finding as the rules make it: a stuck run's figure and severity follow its length,
    a near miss's its closest tick's (and its evidence)."""
    i = incident(kind, n * 1000, ongoing, end_ms=n * 1000 + end_ms)
    if kind == "stuck":
        still_s = (i.end_ms - i.start_ms) / 1000
        return msgspec.structs.replace(
            i, measure=still_s, severity="critical" if still_s >= 300 else "warning"
        )
    at = i.start_ms + round(closest * 1000)
    closest_tick = (PoseRef("a", at, 1.5, -2.0), PoseRef("b", at, 1.5 + closest, -2.0))
    return msgspec.structs.replace(
        i,
        measure=closest,
        evidence=closest_tick,
        severity="critical" if closest < 0.5 else "warning",
    )


@given(steps, st.sets(st.integers(0, 4)))
def test_the_ledger_names_each_finding_as_a_receivers_record_needs(steps, stored) -> None:
    """A receiver that opens on `new`, updates on `changed`, closes on `ended` and drops on
    `retracted` holds every incident found, whether it goes on and its severity as last
    found: a finding that differs from the last alert in neither (a closer near miss of the
    same severity, a longer stuck run) sends none. One the ledger was seeded with (stored
    before a restart) is never announced as new."""
    ledger = AlertLedger()
    seeded = [found_as("stuck", n, True, 5_000, 0.4) for n in stored]
    ledger.seed(seeded)
    record = {i.incident_id: (i.ongoing, i.severity) for i in seeded}  # the receiver's
    for n, kind, ongoing, retract, end_ms, closest in steps:
        i = found_as(kind, n, ongoing, end_ms, closest)
        if retract:
            ((event, _),) = ledger.classify([], [i])
            assert event == "retracted"
            record.pop(i.incident_id, None)
            continue
        alerts = ledger.classify([i], [])
        was = record.get(i.incident_id)
        if was == (i.ongoing, i.severity):
            assert alerts == []
            continue
        ((event, _),) = alerts
        if was is None:
            assert event == "new"
        elif was[0] and not ongoing:
            assert event == "ended"
        else:
            assert event == "changed"
        record[i.incident_id] = (i.ongoing, i.severity)


def test_an_incident_refined_while_it_goes_on_sends_no_alert_until_its_severity_changes() -> None:
    ledger = AlertLedger()
    first = found_as("stuck", 1, True, 30_000, 0.0)
    assert [e for e, _ in ledger.classify([first], [])] == ["new"]
    for end in range(30_500, 300_000, 500):
        assert ledger.classify([found_as("stuck", 1, True, end, 0.0)], []) == []
    critical = found_as("stuck", 1, True, 300_000, 0.0)
    assert [e for e, _ in ledger.classify([critical], [])] == ["changed"]
    near = found_as("near_miss", 2, True, 10_000, 0.8)
    assert [e for e, _ in ledger.classify([near], [])] == ["new"]
    for closer in (0.7, 0.6, 0.55):
        assert ledger.classify([found_as("near_miss", 2, True, 20_000, closer)], []) == []
    assert [e for e, _ in ledger.classify([found_as("near_miss", 2, True, 21_000, 0.4)], [])] == [
        "changed"
    ]
    [(event, last)] = ledger.classify([found_as("near_miss", 2, False, 22_000, 0.3)], [])
    assert event == "ended" and last.measure == 0.3  # the final figures


def test_the_ledger_forgets_what_the_detection_let_go_of() -> None:
    ledger = AlertLedger()
    a, b = incident("offline", 0, True), incident("offline", 1000, True)
    ledger.classify([a, b], [])
    ledger.keep([b.incident_id])
    assert [(e, i.incident_id) for e, i in ledger.classify([a, b], [])] == [("new", a.incident_id)]
