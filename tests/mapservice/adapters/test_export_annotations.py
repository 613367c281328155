"""The operators' side of the exports: the MCAP read back holds the annotations standing at
the window's start and after each edit (foxglove.SceneUpdate on /annotations) and the
commands with the robots' answers (/commands); the tables `annotation-edits` and
`commands` come from ClickHouse's event tables."""

from __future__ import annotations

import csv
import io
import json
import time

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.mcap_annotations import ANNOTATIONS_TOPIC, COMMANDS_SCHEMA, COMMANDS_TOPIC
from mapservice.adapters.mcap_export import ReplaySources, export_mcap
from mapservice.adapters.table_export import export_table
from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationRemoved,
    PointOfInterest,
    Zone,
)
from mapservice.core.commands import CommandAcknowledged, CommandFinished, CommandIssued
from mapservice.core.events import make_envelope
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import meta_event, pose_event

T0 = (time.time_ns() // 1_000_000 // 1000) * 1000 - 3_600_000
PIT = Zone("pit", "keep_out", ((0.0, 3.0), (2.0, 3.0), (2.0, 5.0), (0.0, 5.0)))
AISLE = Zone(
    "aisle 2",
    "speed_limit",
    ((4.0, 0.0), (6.0, 0.0), (6.0, 8.0)),
    speed_limit=0.5,
    speed_unit="m/s",
)
DOCK = PointOfInterest("dock 1", "station", 1.0, 1.0)


def _sources(store) -> ReplaySources:
    """Every role a replay export reads, from the test's one store."""
    return ReplaySources(store, store, store, store, store, store)


def _at(t_ms: int, payload, who: str = "operator:ab12"):
    return make_envelope(who, t_ms, t_ms, payload)


def history(store) -> None:
    """A map, a robot's poses through the window (T0 .. T0+60 s); the pit and the dock made
    before the window, the aisle's speed zone made at +20 s, the pit removed and the dock
    moved at +40 s; a pause to agv-1 at +10 s, acknowledged at +11 s, done at +12 s."""
    store.append([meta_event(T0 - 10_000)])
    store.append(
        [
            _at(T0 - 5000, AnnotationCreated("z-pit", "operator:ab12", PIT)),
            _at(T0 - 4000, AnnotationCreated("p-dock", "operator:ab12", DOCK)),
            _at(T0 + 20_000, AnnotationCreated("z-aisle", "operator:cd34", AISLE)),
            _at(T0 + 40_000, AnnotationRemoved("z-pit", "operator:cd34")),
            _at(
                T0 + 40_000,
                AnnotationChanged(
                    "p-dock", "operator:cd34", PointOfInterest("dock 1", "station", 3.0, 1.5)
                ),
            ),
        ]
    )
    store.append(
        [
            _at(
                T0 + 10_000,
                CommandIssued("c-1", "agv-1", "pause", "operator:ab12", T0 + 10_000),
                "agv-1",
            ),
            _at(T0 + 11_000, CommandAcknowledged("c-1", "agv-1", "accepted"), "agv-1"),
            _at(T0 + 12_000, CommandFinished("c-1", "agv-1", "done"), "agv-1"),
        ]
    )
    store.append([pose_event("agv-1", T0 + i * 1000, x=float(i)) for i in range(60)])


def read_back(data: bytes) -> tuple[list[tuple[str, int, object]], dict[str, dict]]:
    """(topic, log time ms, message) in file order, and the JSON schemas by name."""
    protobuf = DecoderFactory()
    out, schemas = [], {}
    for schema, channel, message in make_reader(io.BytesIO(data)).iter_messages():
        if channel.message_encoding == "json":
            schemas[schema.name] = json.loads(schema.data)
            out.append((channel.topic, message.log_time // 1_000_000, json.loads(message.data)))
        else:
            out.append(
                (
                    channel.topic,
                    message.log_time // 1_000_000,
                    protobuf.decoder_for(channel.message_encoding, schema)(message.data),
                )
            )
    return out, schemas


def _standing(update) -> dict[str, dict]:
    """What a SceneUpdate draws: id -> its kind, label(s), line vertices, sphere position."""
    assert [d.type for d in update.deletions] == [1]  # ALL: the update is the whole set
    return {
        e.id: {
            "kind": {m.key: m.value for m in e.metadata}["kind"],
            "texts": [t.text for t in e.texts],
            "lines": [[(p.x, p.y) for p in line.points] for line in e.lines],
            "colors": [(line.color.r, line.color.g, line.color.b) for line in e.lines],
            "spheres": [(s.pose.position.x, s.pose.position.y) for s in e.spheres],
            "frame": e.frame_id,
        }
        for e in update.entities
    }


def test_mcap_holds_the_annotations_at_the_start_and_after_each_edit() -> None:
    store = MemoryStore()
    history(store)
    out = io.BytesIO()
    counts = export_mcap(_sources(store), T0 + 5000, T0 + 50_000, out)
    messages, _ = read_back(out.getvalue())
    updates = [(t, _standing(m)) for topic, t, m in messages if topic == ANNOTATIONS_TOPIC]
    assert [t for t, _ in updates] == [T0 + 5000, T0 + 20_000, T0 + 40_000]
    assert counts.annotation_updates == 3
    start = updates[0][1]
    assert set(start) == {"z-pit", "p-dock"}
    pit = start["z-pit"]
    assert (
        pit["kind"] == "keep_out" and pit["frame"] == "map" and pit["texts"] == ["pit (keep out)"]
    )
    assert pit["lines"] == [list(PIT.polygon)] and pit["colors"][0][0] > 0.8 > pit["colors"][0][1]
    assert start["p-dock"]["spheres"] == [(1.0, 1.0)] and start["p-dock"]["texts"] == [
        "dock 1 (station)"
    ]
    after_create = updates[1][1]
    assert set(after_create) == {"z-pit", "p-dock", "z-aisle"}
    assert after_create["z-aisle"]["texts"] == ["aisle 2 (speed limit 0.5 m/s)"]
    # The pit removed and the dock moved at the same instant: one update with both.
    last = updates[2][1]
    assert set(last) == {"p-dock", "z-aisle"} and last["p-dock"]["spheres"] == [(3.0, 1.5)]
    times = [t for _, t, _ in messages]
    assert times == sorted(times)


def test_mcap_without_annotations_standing_starts_with_none() -> None:
    """A window before any annotation has no /annotations message until the first edit."""
    store = MemoryStore()
    history(store)
    messages, _ = read_back(_export(store, T0 - 9000, T0 - 4500))
    assert [(t, set(_standing(m))) for topic, t, m in messages if topic == ANNOTATIONS_TOPIC] == [
        (T0 - 5000, {"z-pit"})
    ]


def _export(store, from_ms: int, to_ms: int) -> bytes:
    out = io.BytesIO()
    export_mcap(_sources(store), from_ms, to_ms, out)
    return out.getvalue()


def test_mcap_holds_the_commands_and_the_robots_answers_in_time_order() -> None:
    store = MemoryStore()
    history(store)
    messages, schemas = read_back(_export(store, T0, T0 + 60_000))
    commands = [(t, m) for topic, t, m in messages if topic == COMMANDS_TOPIC]
    assert [
        (t, m["event"], m["by"], m["robot_id"], m["kind"], m["status"]) for t, m in commands
    ] == [
        (T0 + 10_000, "issued", "operator:ab12", "agv-1", "pause", "issued"),
        (T0 + 11_000, "ack", "agv-1", "agv-1", "pause", "accepted"),
        (T0 + 12_000, "outcome", "agv-1", "agv-1", "pause", "done"),
    ]
    assert schemas["mapservice.CommandEvent"] == COMMANDS_SCHEMA
    assert all(set(COMMANDS_SCHEMA["required"]) <= set(m) for _, m in commands)
    # A window that starts after the issue still carries the answers (kind unknown there).
    later, _ = read_back(_export(store, T0 + 10_500, T0 + 60_000))
    assert [(m["event"], m["kind"]) for topic, _, m in later if topic == COMMANDS_TOPIC] == [
        ("ack", None),
        ("outcome", None),
    ]


@pytest.fixture(scope="module")
def clickhouse(tmp_path_factory):
    store = ClickHouseStore(
        f"chdb://{tmp_path_factory.mktemp('exports') / 'ch'}", database="opexports"
    )
    store.migrate()
    history(store)
    yield store
    store.close()


def test_annotation_edits_and_commands_export_as_tables(clickhouse) -> None:
    """CSV of the window's edits (who, when, what) and commands (a robot's, if asked);
    Parquet too."""
    window = (T0, T0 + 60_000)
    edits = list(
        csv.DictReader(
            io.StringIO(
                export_table(clickhouse, "annotation-edits", "csv", *window, "agv-1").decode()
            )
        )
    )
    # Only the window's edits (the robot filter does not apply: edits have no robot).
    assert [r["annotation_id"] for r in edits[:1]] == ["z-aisle"]
    assert sorted((r["annotation_id"], r["author"]) for r in edits) == [
        ("p-dock", "operator:cd34"),
        ("z-aisle", "operator:cd34"),
        ("z-pit", "operator:cd34"),
    ]
    assert (
        edits[0]["annotation_id"] == "z-aisle"
        and json.loads(edits[0]["body"])["speed_limit"] == 0.5
    )
    commands = list(
        csv.DictReader(
            io.StringIO(export_table(clickhouse, "commands", "csv", *window, "agv-1").decode())
        )
    )
    assert [(r["event"], r["by"], r["status"]) for r in commands] == [
        ("issued", "operator:ab12", ""),
        ("ack", "agv-1", "accepted"),
        ("outcome", "agv-1", "done"),
    ]
    assert export_table(clickhouse, "commands", "csv", *window, "agv-2").decode().count("\n") == 1
    assert export_table(clickhouse, "annotation-edits", "parquet", *window)[:4] == b"PAR1"
