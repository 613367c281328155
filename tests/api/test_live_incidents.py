"""Incidents on the live stream: each announcement carries the incident exactly as GET
/api/v1/incidents lists it, the relay reads the records as live messages, retractions come
before findings, and records are cut like the batches'."""

from __future__ import annotations

import msgspec
from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.api.routers.incidents import Incident as Listed
from mapservice.api.routers.incidents import _as_of
from mapservice.core.incident_model import KINDS, SEVERITIES, Incident, PoseRef, incident_id
from mapservice.core.live_incidents import incident_records
from mapservice.core.live_messages import live_record_texts

robots = st.lists(
    st.sampled_from(["r1", "r2", "robot-3", "ü"]), min_size=1, max_size=2, unique=True
)
metres = st.floats(-1e4, 1e4, allow_nan=False)


@st.composite
def incidents(draw) -> Incident:
    kind = draw(st.sampled_from(KINDS))
    rs = tuple(sorted(draw(robots)))
    start = draw(st.integers(0, 2**41))
    evidence = tuple(
        PoseRef(
            draw(st.sampled_from(rs)),
            start + draw(st.integers(0, 10**6)),
            draw(metres),
            draw(metres),
        )
        for _ in range(draw(st.integers(1, 3)))
    )
    return Incident(
        incident_id(kind, rs, start),
        kind,
        rs,
        start,
        start + draw(st.integers(0, 10**8)),
        draw(st.booleans()),
        draw(metres),
        draw(metres),
        draw(st.sampled_from(SEVERITIES)),
        draw(st.floats(0, 1e6, allow_nan=False)),
        evidence,
    )


def announced(records: list[bytes]) -> list[dict]:
    """The messages as a live page gets them: through the relay's reading of the records."""
    return [dict(text) for record in records for text in live_record_texts(record)]


@settings(max_examples=60, deadline=None)
@given(st.lists(incidents(), max_size=6), st.lists(incidents(), max_size=3), st.integers(0, 2**41))
def test_an_announcement_lists_the_incident_as_the_api_does(found, retracted, found_ms) -> None:
    messages = announced(incident_records(found, retracted, found_ms))
    assert [(m["type"], m["ts_ms"], m["retracted"]) for m in messages] == [
        ("incident", found_ms, True)
    ] * len(retracted) + [("incident", found_ms, False)] * len(found)
    for m, i in zip(messages, [*retracted, *found], strict=True):
        # As the list shows it when read at its end (the list extends an ongoing silence to now).
        listed = msgspec.json.decode(msgspec.json.encode(_as_of(i, i.end_ms)))
        assert Listed.model_validate(m["incident"]) == Listed.model_validate(listed)


def test_records_are_cut_below_the_limit_and_keep_the_order() -> None:
    found = [
        Incident(
            incident_id("near_miss", ("a", "b"), k),
            "near_miss",
            ("a", "b"),
            k,
            k + 5,
            False,
            1.0,
            2.0,
            "warning",
            0.4,
            (PoseRef("a", k, 1.0, 2.0),),
        )
        for k in range(50)
    ]
    records = incident_records(found, [], 7, max_bytes=1000)
    assert len(records) > 5 and all(len(r) <= 1000 for r in records)
    assert [m["incident"]["start_ms"] for m in announced(records)] == list(range(50))
    assert all(isinstance(msgspec.json.decode(r), list) for r in records)


def test_nothing_found_is_no_record() -> None:
    assert incident_records([], [], 1) == []
