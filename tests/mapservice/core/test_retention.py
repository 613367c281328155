"""The retention's one rule: the gateway refuses exactly the timestamps the history sink
would not store, and only the history's events expire (the map meta and the annotations
are state, kept however old)."""

from __future__ import annotations

import random

import pytest

from mapservice.core.annotations import AnnotationCreated, PointOfInterest
from mapservice.core.commands import CommandAcknowledged, CommandFinished, CommandIssued
from mapservice.core.events import VdaConnectionReported, VdaFactsheetReported, make_envelope
from mapservice.core.retention import DAY_MS, RETAINED_BY_TIME, expired, older_than_retention
from mapservice.core.wire2019 import Limits, Reason, Rejection, check_time, format_timestamp
from tests.conftest import chunk_event, meta_event, pose_event

NOW = 1_795_255_200_000


def offsets(retention_ms: int, seed: int) -> list[int]:
    """Ages around the boundary (a millisecond either side, the boundary itself) and
    random ones within three retentions."""
    rng = random.Random(seed)
    edge = [retention_ms - 1, retention_ms, retention_ms + 1, 0]
    return edge + [rng.randrange(0, 3 * retention_ms) for _ in range(200)]


@pytest.mark.parametrize("retention_days", [1, 7, 24])
def test_the_gateway_refuses_what_the_rule_calls_older_than_the_retention(
    retention_days: int,
) -> None:
    retention_ms = retention_days * DAY_MS
    limits = Limits(retention_ms=retention_ms)
    for age in offsets(retention_ms, retention_days):
        ts = NOW - age
        refused = check_time(format_timestamp(ts), NOW, limits)
        too_old = isinstance(refused, Rejection) and refused.reason == Reason.TIMESTAMP_TOO_OLD
        assert too_old == older_than_retention(ts, NOW, retention_ms) == (age > retention_ms), age


def history_events(t: int) -> list:
    return [
        pose_event("r1", t),
        chunk_event("r1", t, 2, 3),
        make_envelope("r1", t, t, CommandIssued("c1", "r1", "pause", "operator:x", t)),
        make_envelope("r1", t, t, CommandAcknowledged("c1", "r1", "accepted")),
        make_envelope("r1", t, t, CommandFinished("c1", "r1", "done")),
        make_envelope("m/s1", t, t, VdaConnectionReported("m", "s1", "2.0.0", "ONLINE", t)),
    ]


def state_events(t: int) -> list:
    poi = PointOfInterest(name="dock", kind="station", x=1.0, y=2.0, heading=0.0)
    return [
        meta_event(t),
        make_envelope("operator", t, t, AnnotationCreated("p1", "operator:x", poi)),
        make_envelope("m/s1", t, t, VdaFactsheetReported("m", "s1", "2.0.0", "{}")),
    ]


@pytest.mark.parametrize("retention_days", [1, 7, 24])
def test_history_events_expire_with_the_retention_and_state_never(retention_days: int) -> None:
    retention_ms = retention_days * DAY_MS
    for age in offsets(retention_ms, retention_days):
        for event in history_events(NOW - age):
            assert isinstance(event.payload, RETAINED_BY_TIME)
            assert expired(event, NOW, retention_ms) == (age > retention_ms), (event.type, age)
        for event in state_events(NOW - age):
            assert not expired(event, NOW, retention_ms), (event.type, age)
