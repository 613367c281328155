"""Incidents, conflicts and VDA 5050 errors as Foxglove channels, on the memory store with
generated findings: every message is valid against its channel's JSON schema; the MCAP
export holds them; a seek sends the incidents going on at T and the errors standing then;
playing a span sends each start, end, conflict and error of it at its time, among the
poses, however long the step; the live feed sends each announced incident (start, update,
end, retraction) and the conflicts stored since its last re-read, each once."""

from __future__ import annotations

import io
import json
import random

import pytest
from jsonschema import Draft202012Validator
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from mapservice.adapters.foxglove_findings import FoxgloveFindings
from mapservice.adapters.foxglove_replay import ReplaySession
from mapservice.adapters.foxglove_scene import FoxgloveScene
from mapservice.adapters.mcap_channels import (
    CONFLICT_SCHEMA,
    CONFLICTS_TOPIC,
    ERRORS_SCHEMA_NAME,
    INCIDENT_MARKERS_TOPIC,
    INCIDENT_SCHEMA,
    INCIDENTS_TOPIC,
    JSON_SCHEMAS,
    errors_topic,
)
from mapservice.adapters.mcap_export import ReplaySources, export_mcap
from mapservice.adapters.mcap_findings import (
    ERRORS_LOOKBACK_MS,
    incident_doc,
    incident_messages,
    incidents_at,
)
from mapservice.core.incident_model import KINDS, SEVERITIES, Incident, PoseRef, incident_id
from mapservice.core.live_incidents import incident_records
from mapservice.core.live_messages import live_record_texts
from mapservice.core.ports import ConflictRow
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import meta_event, pose_event
from tests.mapservice.adapters.test_foxglove_scene import Recorder

T0 = 1_795_255_200_000
SPAN = 600_000


def sources(store: MemoryStore) -> ReplaySources:
    return ReplaySources(store, store, store, store, store, store)


def valid(schema_name: str, doc: dict) -> bool:
    validator = Draft202012Validator(JSON_SCHEMAS[schema_name])
    return not list(validator.iter_errors(doc))


def random_incident(rng: random.Random) -> Incident:
    kind = rng.choice(KINDS)
    robots = tuple(sorted(rng.sample(["r0", "r1", "r2"], 2 if kind == "near_miss" else 1)))
    # Whole seconds: starts and ends share instants with each other and with the poses.
    start = T0 + rng.randrange(-60, SPAN // 1000) * 1000
    end = start + rng.choice((0, 1000, rng.randrange(0, 200) * 1000))
    evidence = tuple(
        PoseRef(robots[0], t, rng.uniform(0, 20), rng.uniform(0, 20))
        for t in sorted({start, end, rng.randrange(start, end + 1)})
    )
    return Incident(
        incident_id=incident_id(kind, robots, start),
        kind=kind,
        robots=robots,
        start_ms=start,
        end_ms=end,
        ongoing=rng.random() < 0.3,
        x=rng.uniform(0, 20),
        y=rng.uniform(0, 20),
        severity=rng.choice(SEVERITIES),
        measure=rng.uniform(0, 100),
        evidence=evidence,
    )


def vda_errors(store: MemoryStore, rng: random.Random) -> list[tuple[int, int]]:
    """A vehicle's states through the span, some with errors: (time, error count) each."""
    from mapservice.core.events import decode
    from mapservice.core.intake import Intake
    from mapservice.ingest.router import Router
    from mapservice.settings import Settings
    from tests.fixtures import vda5050 as vda

    router, states = Router(Settings(), "gw"), []
    for t in range(T0 - 30_000, T0 + SPAN, 20_000):
        errors = tuple(
            (rng.choice(("WARNING", "FATAL")), f"e{k}", "broke")
            for k in range(rng.choice((0, 1, 2)))
        )
        msg = vda.state("2.0.0", "Acme", "7", t, errors=errors)
        record = router.route("uagv/v2/Acme/7/state", vda.encode(msg), t, Intake())
        store.append([decode(record.value)])
        states.append((t, len(errors)))
    return states


def findings(seed: int) -> tuple[MemoryStore, list[Incident], list[ConflictRow]]:
    """Three robots' poses every 3 s, random incidents (some retracted later), conflicts."""
    rng = random.Random(seed)
    store = MemoryStore()
    store.append([meta_event(T0 - 100_000)])
    store.append(
        [
            pose_event(r, t, x=1.0, y=2.0)
            for r in ("r0", "r1", "r2")
            for t in range(T0, T0 + SPAN, 3_000)
        ]
    )
    incidents = list(
        {
            i.incident_id: i for i in (random_incident(rng) for _ in range(rng.randrange(5, 40)))
        }.values()
    )
    retracted = rng.sample(incidents, len(incidents) // 5)
    store.append_incidents(incidents, T0)
    store.append_incidents([], T0 + 1, retracted)
    kept = [i for i in incidents if i not in retracted]
    conflicts = [
        ConflictRow(rng.randrange(4), rng.randrange(5), t, "r0", t - 1000, "r1")
        for t in sorted({T0 + rng.randrange(SPAN // 1000) * 1000 for _ in range(rng.randrange(10))})
    ]
    store.append_conflicts(conflicts)
    return store, kept, conflicts


def test_the_channels_schemas_are_json_schemas():
    for schema in (INCIDENT_SCHEMA, CONFLICT_SCHEMA):
        Draft202012Validator.check_schema(schema)
        assert JSON_SCHEMAS[schema["title"]] is schema


@pytest.mark.parametrize("seed", range(4))
def test_every_message_is_valid_against_its_channels_schema(seed):
    store, incidents, _ = findings(seed)
    vda_errors(store, random.Random(seed))
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    session = ReplaySession(sources(store), T0, T0 + SPAN)
    scene.draw_at(T0 + 100_000)
    session._play(scene, T0, T0 + SPAN)
    for i in incidents:
        scene.findings.live_incident(
            {"ts_ms": i.end_ms, "retracted": False, "incident": _listed(i)}
        )
    sent = [(top, m) for top, _, m in channels.sent if isinstance(m, dict)]
    names = {INCIDENTS_TOPIC: "mapservice.Incident", CONFLICTS_TOPIC: "mapservice.Conflict"}
    assert {INCIDENTS_TOPIC, errors_topic("Acme:7")} <= {top for top, _ in sent}
    for topic, doc in sent:
        if topic in names:
            assert valid(names[topic], doc), doc
        elif topic.endswith("/errors"):
            assert valid(ERRORS_SCHEMA_NAME, doc), doc
    broken = dict(incident_doc(incidents[0], "start", T0), severity="dire")
    assert not valid("mapservice.Incident", broken)


def _listed(i: Incident) -> dict:
    """An incident as a live message carries it (what core/live_incidents.py encodes)."""
    [record] = incident_records([i], [], i.end_ms)
    [message] = live_record_texts(record)
    return dict(message["incident"])


def test_the_mcap_export_holds_the_incidents_and_conflicts_of_its_window():
    """Going on at the window's start (at that instant), each start and end inside it, an
    incident over as it began once, ongoing ones without an end, retracted ones not at
    all; every conflict of the window at its time; the channels carry their JSON schema."""
    store = MemoryStore()
    store.append([meta_event(T0 - 100_000)])
    w0, w1 = T0, T0 + 60_000

    def incident(kind: str, start: int, end: int, ongoing: bool = False) -> Incident:
        return Incident(
            incident_id(kind, ("a",), start), kind, ("a",), start, end, ongoing, 1.0, 2.0,
            "warning", 3.0, (PoseRef("a", start, 1.0, 2.0), PoseRef("a", end, 1.5, 2.0)),
        )  # fmt: skip

    before = incident("stuck", w0 - 20_000, w0 + 10_000)
    inside = incident("near_miss", w0 + 5_000, w0 + 8_000)
    instant = incident("vda_error", w0 + 9_000, w0 + 9_000)
    going = incident("offline", w0 + 30_000, w0 + 40_000, ongoing=True)
    after = incident("battery_low", w0 + 50_000, w1 + 5_000)
    outside = incident("conflict", w1 + 1_000, w1 + 2_000)
    gone = incident("zone_violation", w0 + 1_000, w0 + 2_000)
    store.append_incidents([before, inside, instant, going, after, outside, gone], w0)
    store.append_incidents([], w0 + 1, [gone])
    conflicts = [
        ConflictRow(0, 1, w0 + 3_000, "a", w0 + 2_500, "b"),
        ConflictRow(1, 1, w1 + 3_000, "a", w1 + 2_500, "b"),
    ]
    store.append_conflicts(conflicts)
    out = io.BytesIO()
    counts = export_mcap(sources(store), w0, w1, out)
    reader = make_reader(io.BytesIO(out.getvalue()))
    summary = reader.get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    for topic, schema in ((INCIDENTS_TOPIC, INCIDENT_SCHEMA), (CONFLICTS_TOPIC, CONFLICT_SCHEMA)):
        assert channels[topic].message_encoding == "json"
        stored = summary.schemas[channels[topic].schema_id]
        assert stored.encoding == "jsonschema" and json.loads(stored.data) == schema
    read = [
        (c.topic, m.log_time // 1_000_000, json.loads(m.data))
        for _, c, m in make_reader(io.BytesIO(out.getvalue())).iter_messages()
        if c.topic in (INCIDENTS_TOPIC, CONFLICTS_TOPIC)
    ]
    got = [(t, m["event"], m["id"], m["end_ms"]) for top, t, m in read if top == INCIDENTS_TOPIC]
    assert got == [
        (w0, "ongoing", before.incident_id, None),
        (w0 + 5_000, "start", inside.incident_id, None),
        (w0 + 8_000, "end", inside.incident_id, w0 + 8_000),
        (w0 + 9_000, "end", instant.incident_id, w0 + 9_000),
        (w0 + 10_000, "end", before.incident_id, w0 + 10_000),
        (w0 + 30_000, "start", going.incident_id, None),
        (w0 + 50_000, "start", after.incident_id, None),
    ]
    # What was known then: no evidence from after the message's time.
    for top, t, m in read:
        if top == INCIDENTS_TOPIC:
            assert all(e["ts_ms"] <= t for e in m["evidence"]) and m["evidence"]
    assert [(t, m["row"], m["column"]) for top, t, m in read if top == CONFLICTS_TOPIC] == [
        (w0 + 3_000, 0, 1)
    ]
    # Each incident message's marker: drawn while it goes on, deleted at its end.
    decoder = DecoderFactory()
    markers = [
        (m.log_time // 1_000_000, decoder.decoder_for(c.message_encoding, s)(m.data))
        for s, c, m in make_reader(io.BytesIO(out.getvalue())).iter_messages()
        if c.topic == INCIDENT_MARKERS_TOPIC
    ]
    assert [(t, [e.id for e in u.entities], [d.id for d in u.deletions]) for t, u in markers] == [
        (t, [] if event == "end" else [id_], [id_] if event == "end" else [])
        for t, event, id_, _ in got
    ]
    assert (counts.incidents, counts.incident_markers, counts.conflicts) == (7, 7, 1)


@pytest.mark.parametrize("seed", range(6))
def test_a_seek_sends_the_incidents_going_on_and_the_errors_standing_at_t(seed):
    store, incidents, _ = findings(seed)
    states = vda_errors(store, random.Random(seed))
    rng = random.Random(seed)
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    for at in [rng.randrange(T0 - 10_000, T0 + SPAN) for _ in range(6)] + [
        rng.choice(incidents).start_ms
    ]:
        channels.sent.clear()
        scene.draw_at(at)
        sent = channels.on(INCIDENTS_TOPIC)
        # An ongoing one is going on after its stored end too (only where it was last found).
        assert {m["id"] for _, m in sent} == {
            i.incident_id for i in incidents if i.start_ms <= at and (at <= i.end_ms or i.ongoing)
        }
        for t, m in sent:
            i = next(i for i in incidents if i.incident_id == m["id"])
            ended = not i.ongoing and i.end_ms <= at
            assert t == at and (m["ongoing"], m["end_ms"]) == (
                not ended,
                i.end_ms if ended else None,
            )
        standing = [
            s
            for k, s in enumerate(states)
            if at - ERRORS_LOOKBACK_MS <= s[0] <= at and (s[1] or (k and states[k - 1][1]))
        ]
        assert [(t, m["count"]) for t, m in channels.on(errors_topic("Acme:7"))] == standing[-1:]
        # A client that subscribes now gets the incidents going on again.
        channels.sent.clear()
        scene.resend(INCIDENTS_TOPIC)
        assert sorted(m["id"] for _, m in channels.on(INCIDENTS_TOPIC)) == sorted(
            m["id"] for _, m in sent if not m["event"] == "end"
        )
        assert incidents_at(store, at) == [
            (at, INCIDENTS_TOPIC, "mapservice.Incident", m) for _, m in sent
        ]


@pytest.mark.parametrize("seed", range(6))
def test_playing_sends_every_start_end_conflict_and_error_of_the_span_at_its_time(seed):
    """Steps of any length (a high speed is a long step): each incident's start and end
    once, at its time, every conflict and error instant; in time order among the poses."""
    store, incidents, conflicts = findings(seed)
    states = vda_errors(store, random.Random(seed))
    rng = random.Random(seed)
    session = ReplaySession(sources(store), T0, T0 + SPAN)
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    at = T0 + rng.randrange(0, 100_000)
    scene.draw_at(at)
    channels.sent.clear()
    cursor = at
    while cursor < T0 + SPAN:
        end = min(cursor + rng.choice((100, 1_000, 6_000, 60_000, 250_000)), T0 + SPAN)
        session._play(scene, cursor, end)
        cursor = end
    starts = [(t, m["id"]) for t, m in channels.on(INCIDENTS_TOPIC) if m["event"] == "start"]
    ends = [(t, m["id"]) for t, m in channels.on(INCIDENTS_TOPIC) if m["event"] == "end"]
    assert sorted(starts) == sorted(
        (i.start_ms, i.incident_id)
        for i in incidents
        if at <= i.start_ms and not (not i.ongoing and i.end_ms == i.start_ms)
    )
    assert sorted(ends) == sorted(
        (i.end_ms, i.incident_id)
        for i in incidents
        if not i.ongoing and at <= i.end_ms < T0 + SPAN and i.end_ms >= i.start_ms
    )
    assert [(t, m["row"], m["column"]) for t, m in channels.on(CONFLICTS_TOPIC)] == [
        (c.ts_ms, c.row, c.column) for c in conflicts if c.ts_ms >= at
    ]
    error_instants = [t for t, _ in channels.on(errors_topic("Acme:7"))]
    assert error_instants == [
        t for k, (t, n) in enumerate(states) if t >= at and (n or (k and states[k - 1][1]))
    ]
    markers = channels.on(INCIDENT_MARKERS_TOPIC)
    assert [(t, [e.id for e in u.entities] or [d.id for d in u.deletions]) for t, u in markers] == [
        (t, [m["id"]]) for t, m in channels.on(INCIDENTS_TOPIC)
    ]
    order = [
        t
        for top, t, _ in channels.sent
        if top.endswith("/pose") or top in (INCIDENTS_TOPIC, CONFLICTS_TOPIC)
    ]
    assert order == sorted(order)


def test_the_live_feed_sends_each_announced_incident_and_the_new_conflicts_once():
    """The live stream's incident messages (as the relay hands them on): a start, updates
    while it goes on, its end; a retraction drops it from what a late subscriber gets; the
    conflicts and errors stored since the last re-read go out once."""
    from mapservice.adapters.foxglove_live import FoxgloveLive

    store = MemoryStore()
    store.append([meta_event(T0 - 100_000)])
    now = [T0 + 100_000]
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    feed = FoxgloveLive(scene, lambda: now[0], grid_every_s=1e-9, annotations_every_s=1e-9)

    def stuck(end: int, ongoing: bool) -> Incident:
        return Incident(
            incident_id("stuck", ("a",), T0), "stuck", ("a",), T0, end, ongoing, 1.0, 2.0,
            "warning", (end - T0) / 1000, (PoseRef("a", T0, 1.0, 2.0),),
        )  # fmt: skip

    near = Incident(
        incident_id("near_miss", ("a", "b"), T0 + 1), "near_miss", ("a", "b"), T0 + 1, T0 + 2,
        False, 1.0, 2.0, "critical", 0.5, (PoseRef("a", T0 + 1, 1.0, 2.0),),
    )  # fmt: skip

    def live(found, retracted, at):
        return [m for r in incident_records(found, retracted, at) for m in live_record_texts(r)]

    try:
        feed._draw_now()
        feed._apply(live([stuck(T0 + 40_000, True)], [], T0 + 40_000))
        feed._apply(live([stuck(T0 + 50_000, True), near], [], T0 + 50_000))
        mark = len(channels.sent)
        scene.resend(INCIDENTS_TOPIC)  # a late subscriber: the incident going on
        scene.resend(INCIDENT_MARKERS_TOPIC)  # and its marker
        [(top, _, doc), (marker_top, _, marker)] = channels.sent[mark:]
        assert (top, doc["id"]) == (INCIDENTS_TOPIC, stuck(0, True).incident_id)
        assert (marker_top, [e.id for e in marker.entities]) == (
            INCIDENT_MARKERS_TOPIC,
            [doc["id"]],
        )
        del channels.sent[mark:]
        feed._apply(live([], [stuck(T0 + 50_000, True)], T0 + 60_000))
        feed._apply(live([stuck(T0 + 70_000, False)], [], T0 + 70_000))
        store.append_conflicts([ConflictRow(0, 0, T0 + 90_000, "a", T0 + 89_000, "b")])
        feed._apply([])
        store.append_conflicts([ConflictRow(0, 1, T0 + 95_000, "a", T0 + 94_000, "b")])  # late
        now[0] = T0 + 120_000
        feed._apply([])
        feed._apply([])
    finally:
        feed.close()
    assert len(channels.on(INCIDENT_MARKERS_TOPIC)) == len(channels.on(INCIDENTS_TOPIC))
    sent = [(t, m["event"], m["kind"], m["end_ms"]) for t, m in channels.on(INCIDENTS_TOPIC)]
    assert sent == [
        (T0 + 40_000, "start", "stuck", None),
        (T0 + 50_000, "update", "stuck", None),
        (T0 + 50_000, "end", "near_miss", T0 + 2),
        (T0 + 60_000, "retracted", "stuck", None),
        (T0 + 70_000, "end", "stuck", T0 + 70_000),
    ]
    for _, m in channels.on(INCIDENTS_TOPIC):
        assert valid("mapservice.Incident", m)
    assert [(t, m["column"]) for t, m in channels.on(CONFLICTS_TOPIC)] == [
        (T0 + 90_000, 0),
        (T0 + 95_000, 1),
    ]
    channels.sent.clear()
    scene.resend(INCIDENTS_TOPIC)
    assert channels.sent == []


def test_messages_of_a_span_are_in_time_order_with_those_going_on_first():
    store, _, _ = findings(3)
    for a in range(T0 - 10_000, T0 + SPAN, 97_000):
        messages = incident_messages(store, a, a + 150_000)
        times = [t for t, _, _, _ in messages]
        assert times == sorted(times) and all(a <= t < a + 150_000 for t in times)
        assert all(
            m["event"] == "ongoing" for t, _, _, m in messages if t == a and m["start_ms"] < a
        )


def test_findings_resend_nothing_for_a_topic_not_theirs():
    channels = Recorder()
    findings_view = FoxgloveFindings(channels, sources(MemoryStore()))  # type: ignore[arg-type]
    assert not findings_view.resend("/map")
    assert findings_view.resend(CONFLICTS_TOPIC) and channels.sent == []


def test_a_malformed_incident_message_is_skipped_and_the_rest_of_its_batch_drawn():
    from mapservice.adapters.foxglove_live import FoxgloveLive
    from mapservice.adapters.mcap_channels import pose_topic
    from mapservice.core.live_messages import live_records

    store = MemoryStore()
    store.append([meta_event(T0 - 100_000)])
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    feed = FoxgloveLive(scene, lambda: T0, grid_every_s=3600, annotations_every_s=3600)
    [pose] = [
        m for r in live_records([pose_event("a", T0, x=1.0, y=2.0)]) for m in live_record_texts(r)
    ]
    bad = {"type": "incident", "ts_ms": T0, "retracted": False, "incident": {"id": "x"}}
    try:
        feed._apply([bad, pose])
    finally:
        feed.close()
    assert channels.on(INCIDENTS_TOPIC) == [] and len(channels.on(pose_topic("a"))) == 1


@pytest.mark.parametrize("seed", range(4))
def test_a_live_feed_no_client_listens_to_reads_no_findings_until_one_does(seed):
    """With no client connected the live feed's re-reads read neither conflicts nor VDA 5050
    facts; once a client listens, the next re-read sends each vehicle's standing errors
    and the conflicts of the last `LATE_MS`, as a feed that never paused would have."""
    from mapservice.adapters.foxglove_findings import LATE_MS
    from mapservice.adapters.foxglove_live import FoxgloveLive
    from mapservice.adapters.mcap_findings import vda_errors_at

    rng = random.Random(seed)
    store = MemoryStore()
    store.append([meta_event(T0 - 100_000)])
    vda_errors(store, rng)
    reads: list[str] = []
    conflicts, vda_fleet_facts = store.conflicts, store.vda_fleet_facts
    store.conflicts = lambda *a, **k: reads.append("conflicts") or conflicts(*a, **k)  # type: ignore[method-assign]
    store.vda_fleet_facts = lambda *a, **k: reads.append("vda") or vda_fleet_facts(*a, **k)  # type: ignore[method-assign]
    now = [T0 + 100_000]
    channels = Recorder()
    channels.clients = False
    feed = FoxgloveLive(
        FoxgloveScene(channels, sources(store)),  # type: ignore[arg-type]
        lambda: now[0],
        grid_every_s=1e-9,
        annotations_every_s=1e-9,
    )
    try:
        feed._draw_now()
        reads.clear()
        recent = T0 + SPAN - rng.randrange(1, LATE_MS // 5_000) * 5_000  # one of the ticks
        for t in range(T0 + 100_000, T0 + SPAN, 5_000):
            now[0] = t
            if t == T0 + 300_000:
                store.append_conflicts([ConflictRow(0, 0, t, "a", t - 1_000, "b")])  # long ago
            if t == recent:
                store.append_conflicts([ConflictRow(1, 2, t, "a", t - 1_000, "b")])
            feed._apply([])
        assert reads == []
        channels.sent.clear()
        channels.clients = True
        now[0] = T0 + SPAN
        feed._apply([])
    finally:
        feed.close()
    assert "conflicts" in reads and "vda" in reads
    assert [(t, m["column"]) for t, m in channels.on(CONFLICTS_TOPIC)] == [(recent, 2)]
    standing = {topic: doc for _, topic, _, doc in vda_errors_at(store, T0 + SPAN)}
    sent = {top: doc for top, _, doc in channels.sent if top in standing}
    assert sent == standing
