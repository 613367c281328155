"""The export routes: MCAP of a window over any store, tables where ClickHouse writes them,
clear 4xx for bad windows."""

from __future__ import annotations

import io
import random
import re
from datetime import datetime

from fastapi.testclient import TestClient
from mcap.reader import make_reader

from mapservice.api.app import create_app
from mapservice.api.routers.exports import utc_file_time
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event, meta_event, pose_event

T0 = 1_795_255_200_000


def client(store) -> TestClient:
    return TestClient(create_app(Settings(), store))


def messages_by_topic(mcap: bytes) -> dict[str, int]:
    """An MCAP download's message count per topic, from its summary."""
    summary = make_reader(io.BytesIO(mcap)).get_summary()
    return {
        summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
    }


def test_export_file_names_read_their_span_in_utc() -> None:
    """An export's file name holds its span as readable UTC (no epoch milliseconds, no
    colons), exact to the millisecond: parsed back, it is the instant asked for."""
    rng = random.Random(5)
    for _ in range(2000):
        ms = rng.randrange(1_700_000_000_000, 1_900_000_000_000)
        if rng.random() < 0.3:
            ms -= ms % 1000
        text = utc_file_time(ms)
        m = re.fullmatch(r"(\d{4}-\d\d-\d\d)_(\d\d)-(\d\d)-(\d\d)(?:\.(\d{3}))?", text)
        assert m, text
        day, h, mi, sec, frac = m.groups()
        at = datetime.fromisoformat(f"{day}T{h}:{mi}:{sec}+00:00")
        assert int(at.timestamp()) * 1000 + int(frac or 0) == ms
        assert (frac is None) == (ms % 1000 == 0)


def test_replay_mcap_is_a_download_of_the_window() -> None:
    """GET /api/v1/exports/replay.mcap: an attachment with the map and the window's poses."""
    store = MemoryStore()
    store.append(
        [meta_event(T0 - 1000), chunk_event("a", T0 - 500)]
        + [pose_event("a", T0 + i * 1000) for i in range(10)]
    )
    reply = client(store).get("/api/v1/exports/replay.mcap", params={"from": T0, "to": T0 + 5000})
    assert reply.status_code == 200 and reply.headers["content-type"] == "application/x-mcap"
    assert reply.headers["content-disposition"].endswith(
        f'replay_{utc_file_time(T0)}_to_{utc_file_time(T0 + 5000)}_UTC.mcap"'
    )
    assert messages_by_topic(reply.content) == {
        "/map": 1,
        "/robots/a/pose": 5,
        "/robots/a/state": 5,
        "/tf": 5,  # each pose's transform, map -> a/base_link
    }


def test_replay_mcap_refuses_windows_it_cannot_serve() -> None:
    """Longer than a day, reversed, or before a map exists: 4xx with a reason."""
    c = client(MemoryStore())
    assert (
        c.get(
            "/api/v1/exports/replay.mcap", params={"from": T0, "to": T0 + 2 * 86_400_000}
        ).status_code
        == 400
    )
    assert (
        c.get("/api/v1/exports/replay.mcap", params={"from": T0, "to": T0 - 1}).status_code == 400
    )
    no_map = c.get("/api/v1/exports/replay.mcap", params={"from": T0, "to": T0 + 1000})
    assert no_map.status_code == 409 and "no map geometry" in no_map.json()["detail"]


def test_table_exports_name_what_they_need() -> None:
    """Tables come from ClickHouse's views: on another store a 501 says so; unknown names 422."""
    c = client(MemoryStore())
    reply = c.get("/api/v1/exports/tables/robot-poses", params={"from": T0, "to": T0 + 1000})
    assert reply.status_code == 501 and "ClickHouse" in reply.json()["detail"]
    assert (
        c.get("/api/v1/exports/tables/poses; DROP", params={"from": T0, "to": T0 + 1}).status_code
        == 422
    )
    for dataset in ("annotation-edits", "commands"):  # the operators' events are datasets too
        assert (
            c.get(
                f"/api/v1/exports/tables/{dataset}", params={"from": T0, "to": T0 + 1000}
            ).status_code
            == 501
        )
    assert (
        c.get(
            "/api/v1/exports/tables/robot-poses",
            params={"from": T0, "to": T0 + 1, "format": "xlsx"},
        ).status_code
        == 422
    )


def test_replay_mcap_refuses_instants_past_2262() -> None:
    """Instants whose nanoseconds overflow MCAP's fields are a 400 before any byte is sent
    (the fuzzer found a 500 mid-stream for 2e13 and 3e14 ms)."""
    store = MemoryStore()
    store.append([meta_event(T0 - 1000), pose_event("a", T0)])
    c = client(store)
    for instant in (20_000_000_000_000, 300_000_000_000_000, -1):
        reply = c.get("/api/v1/exports/replay.mcap", params={"from": instant, "to": instant})
        assert reply.status_code == 400, (instant, reply.status_code)
        assert "between 1970 and 2262" in reply.json()["detail"]
    assert (
        c.get("/api/v1/exports/replay.mcap", params={"from": "9" * 5000, "to": T0}).status_code
        == 400
    )


def test_replay_mcap_carries_the_operators_annotations_and_commands() -> None:
    """The download holds /annotations (the zone standing at the start) and /commands."""
    from mapservice.core.annotations import AnnotationCreated, Zone
    from mapservice.core.commands import CommandIssued
    from mapservice.core.events import make_envelope

    zone = Zone("pit", "keep_out", ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0)))
    store = MemoryStore()
    store.append(
        [
            meta_event(T0 - 1000),
            pose_event("a", T0),
            make_envelope(
                "operator:x", T0 - 500, T0 - 500, AnnotationCreated("z1", "operator:x", zone)
            ),
            make_envelope(
                "a", T0 + 100, T0 + 100, CommandIssued("c1", "a", "pause", "operator:x", T0 + 100)
            ),
        ]
    )
    reply = client(store).get("/api/v1/exports/replay.mcap", params={"from": T0, "to": T0 + 1000})
    by_topic = messages_by_topic(reply.content)
    summary = make_reader(io.BytesIO(reply.content)).get_summary()
    assert by_topic["/annotations"] == 1 and by_topic["/commands"] == 1
    assert {
        summary.schemas[c.schema_id].name
        for c in summary.channels.values()
        if c.topic == "/annotations"
    } == {"foxglove.SceneUpdate"}
