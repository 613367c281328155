"""Exports: MCAP read back with the mcap library holds the window's map and poses; CSV and
Parquet come from the analysts' views, limited to the window."""

from __future__ import annotations

import csv
import io
import json
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.mcap_channels import (
    CONNECTION_SCHEMA,
    ERRORS_SCHEMA,
    MAP_TOPIC,
    STATE_SCHEMA,
    TF_TOPIC,
    connection_topic,
    errors_topic,
    path_topic,
    pose_topic,
    robot_frame,
    state_topic,
)
from mapservice.adapters.mcap_export import ReplaySources, export_mcap
from mapservice.adapters.table_export import export_table
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event, meta_event, pose_event

T0 = (time.time_ns() // 1_000_000 // 1000) * 1000 - 3_600_000


def _sources(store) -> ReplaySources:
    """Every role a replay export reads, from the test's one store."""
    return ReplaySources(store, store, store, store, store, store)


def history(store) -> None:
    """Map 4 x 5 chunks of 100 px; chunk (0,0) before the window, (1,2) changed twice inside
    it, two robots reporting every second from T0 to T0 + 60 s."""
    store.append([meta_event(T0 - 10_000)])
    store.append(
        [
            chunk_event("a", T0 - 5000, 0, 0, bytes([0]) * 10_000),
            chunk_event("a", T0 + 20_000, 1, 2, bytes([100]) * 10_000),
            chunk_event("b", T0 + 45_000, 1, 2, bytes([254]) * 10_000),
        ]
    )
    store.append(
        [
            pose_event(robot, T0 + i * 1000, x=float(i), y=2.0 + (robot == "b"))
            for i in range(60)
            for robot in ("a", "b")
        ]
    )


def read_mcap(data: bytes) -> list[tuple[str, int, object]]:
    """(topic, log time in ms, message): protobuf decoded with its schema, JSON parsed."""
    protobuf = DecoderFactory()
    out = []
    for schema, channel, message in make_reader(io.BytesIO(data)).iter_messages():
        if channel.message_encoding == "json":
            decoded = json.loads(message.data)
        else:
            decoded = protobuf.decoder_for(channel.message_encoding, schema)(message.data)
        out.append((channel.topic, message.log_time // 1_000_000, decoded))
    return out


def grid_pixels(grid) -> np.ndarray:
    """The grid back as an image (row 0 at the top, as the map file)."""
    rows = len(grid.data) // grid.row_stride
    return np.flipud(np.frombuffer(grid.data, dtype=np.uint8).reshape(rows, grid.column_count))


def test_mcap_holds_the_map_and_every_pose_of_the_window() -> None:
    """Read back with `mcap`: grids at the start and after changes, poses for each robot."""
    store = MemoryStore()
    history(store)
    out = io.BytesIO()
    counts = export_mcap(_sources(store), T0 + 10_000, T0 + 50_000, out, grid_every_ms=10_000)
    messages = read_mcap(out.getvalue())
    grids = [(t, m) for topic, t, m in messages if topic == MAP_TOPIC]
    poses = [(topic, t, m) for topic, t, m in messages if topic.endswith("/pose")]
    assert counts.poses == len(poses) == 2 * 40
    assert {topic for topic, _, _ in poses} == {pose_topic("a"), pose_topic("b")}
    first = next(m for topic, t, m in poses if topic == pose_topic("a") and t == T0 + 25_000)
    assert (first.pose.position.x, first.pose.position.y, first.frame_id) == (25.0, 2.0, "map")
    # The start: chunk (0,0) as written before the window, (1,2) still unknown (205).
    start = grid_pixels(grids[0][1])
    assert grids[0][0] == T0 + 10_000 and start.shape == (400, 500)
    assert (start[0:100, 0:100] == 0).all() and (start[100:200, 200:300] == 205).all()
    assert grids[0][1].cell_size.x == pytest.approx(0.05) and grids[0][
        1
    ].pose.position.x == pytest.approx(-1.5)
    # After the first change (T0+20 s) and at the end: the later content wins.
    assert any((grid_pixels(m)[100:200, 200:300] == 100).all() for t, m in grids if t < T0 + 45_000)
    assert (grid_pixels(grids[-1][1])[100:200, 200:300] == 254).all()
    assert counts.chunk_changes == 2
    times = [t for _, t, _ in messages]
    assert times == sorted(times)  # log times in order, as players expect
    # Each pose with the robot's frame in the map, at the same instant and place.
    transforms = [(t, m) for topic, t, m in messages if topic == TF_TOPIC]
    assert counts.transforms == len(transforms) == len(poses)
    for (topic, t, pose), (tf_t, tf) in zip(poses, transforms):
        robot = topic.split("/")[2]
        assert (tf_t, tf.parent_frame_id, tf.child_frame_id) == (t, "map", robot_frame(robot))
        assert (tf.translation.x, tf.translation.y, tf.rotation.w) == (
            pose.pose.position.x,
            pose.pose.position.y,
            pose.pose.orientation.w,
        )


def test_mcap_holds_battery_charging_loaded_and_planned_paths() -> None:
    """Per robot a JSON state channel (its JSON schema in the file) with battery in % and
    the charging and loaded flags of every pose, and its planned path as
    foxglove.PosesInFrame each time the path changes."""
    store = MemoryStore()
    store.append([meta_event(T0 - 10_000)])
    store.append(
        [
            pose_event(
                "a",
                T0 + i * 1000,
                x=float(i),
                battery_level=0.5 - i / 100,
                charging=i >= 3,
                loaded="unknown" if i == 1 else i % 2 == 0,
                path=((1.0, 2.0), (3.0, 4.5)) if i < 3 else ((3.0, 4.5), (6.0, 1.0)),
            )
            for i in range(5)
        ]
    )
    out = io.BytesIO()
    counts = export_mcap(_sources(store), T0, T0 + 5_000, out)
    summary = make_reader(io.BytesIO(out.getvalue())).get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    state = channels[state_topic("a")]
    assert state.message_encoding == "json"
    schema = summary.schemas[state.schema_id]
    assert schema.encoding == "jsonschema" and json.loads(schema.data) == STATE_SCHEMA
    assert "%" in STATE_SCHEMA["properties"]["battery_percent"]["description"]
    assert summary.schemas[channels[path_topic("a")].schema_id].name == "foxglove.PosesInFrame"
    messages = read_mcap(out.getvalue())
    states = [m for topic, _, m in messages if topic == state_topic("a")]
    assert [s["battery_percent"] for s in states] == [50.0, 49.0, 48.0, 47.0, 46.0]
    assert [s["charging"] for s in states] == [False, False, False, True, True]
    assert [s["loaded"] for s in states] == [True, "unknown", True, False, True]
    paths = [
        (t, [(p.position.x, p.position.y) for p in m.poses])
        for topic, t, m in messages
        if topic == path_topic("a")
    ]
    assert paths == [(T0, [(1.0, 2.0), (3.0, 4.5)]), (T0 + 3000, [(3.0, 4.5), (6.0, 1.0)])]
    assert (counts.states, counts.paths) == (5, 2)


def test_mcap_holds_vda_vehicles_errors_and_connection_states() -> None:
    """A VDA 5050 vehicle's errors and warnings (each state's active list, an empty list
    when a state clears them) and its connection states (offline when the last will was
    received) as JSON channels with their JSON schemas, read back with `mcap`."""
    from mapservice.core.events import decode
    from mapservice.core.intake import Intake
    from mapservice.ingest.router import Router
    from mapservice.settings import Settings
    from tests.fixtures import vda5050 as vda

    store, router = MemoryStore(), Router(Settings(), "gw")
    store.append([meta_event(T0 - 10_000)])
    v, m, s = "2.0.0", "Acme", "7"
    for subtopic, msg, received in [
        ("connection", vda.connection(v, m, s, T0 + 500, "ONLINE"), T0 + 500),
        ("state", vda.state(v, m, s, T0 + 1000), T0 + 1000),
        (
            "state",
            vda.state(
                v,
                m,
                s,
                T0 + 2000,
                errors=(("WARNING", "lowBattery", "charge me"), ("FATAL", "bumper", "hit")),
            ),
            T0 + 2000,
        ),
        (
            "state",
            vda.state(v, m, s, T0 + 3000, errors=(("WARNING", "lowBattery", "charge me"),)),
            T0 + 3000,
        ),
        ("state", vda.state(v, m, s, T0 + 4000), T0 + 4000),
        ("connection", vda.connection(v, m, s, T0 + 500, "CONNECTIONBROKEN"), T0 + 4500),
    ]:
        record = router.route(f"uagv/v2/{m}/{s}/{subtopic}", vda.encode(msg), received, Intake())
        store.append([decode(record.value)])
    out = io.BytesIO()
    counts = export_mcap(_sources(store), T0, T0 + 5_000, out)
    summary = make_reader(io.BytesIO(out.getvalue())).get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    for topic, schema in (
        (errors_topic("Acme:7"), ERRORS_SCHEMA),
        (connection_topic("Acme:7"), CONNECTION_SCHEMA),
    ):
        assert channels[topic].message_encoding == "json"
        stored = summary.schemas[channels[topic].schema_id]
        assert stored.encoding == "jsonschema" and json.loads(stored.data) == schema
    messages = read_mcap(out.getvalue())
    errors = [(t, m) for topic, t, m in messages if topic == errors_topic("Acme:7")]
    assert errors == [
        (
            T0 + 2000,
            {
                "count": 2,
                "fatal": 1,
                "errors": [
                    {"level": "FATAL", "type": "bumper", "description": "hit"},
                    {"level": "WARNING", "type": "lowBattery", "description": "charge me"},
                ],
            },
        ),
        (
            T0 + 3000,
            {
                "count": 1,
                "fatal": 0,
                "errors": [{"level": "WARNING", "type": "lowBattery", "description": "charge me"}],
            },
        ),
        (T0 + 4000, {"count": 0, "fatal": 0, "errors": []}),
    ]
    connection = [(t, m) for topic, t, m in messages if topic == connection_topic("Acme:7")]
    assert connection == [
        (T0 + 500, {"state": "ONLINE", "online": True, "sent_ms": T0 + 500}),
        (T0 + 4500, {"state": "CONNECTIONBROKEN", "online": False, "sent_ms": T0 + 500}),
    ]
    assert (counts.vda_errors, counts.vda_connections, counts.poses) == (3, 2, 4)
    times = [t for _, t, _ in messages]
    assert times == sorted(times)


def test_mcap_without_a_map_geometry_is_refused() -> None:
    """No meta yet: a clear error instead of an empty file."""
    with pytest.raises(ValueError, match="no map geometry"):
        export_mcap(_sources(MemoryStore()), T0, T0 + 1000, io.BytesIO())


def test_mcap_pages_through_more_poses_than_a_page() -> None:
    """Paging never drops or repeats a pose, even when a page ends mid-instant."""
    store = MemoryStore()
    history(store)
    out = io.BytesIO()
    counts = export_mcap(_sources(store), T0, T0 + 60_000, out, page=7)
    assert counts.poses == 120
    stamps = [(topic, t) for topic, t, _ in read_mcap(out.getvalue()) if topic.endswith("/pose")]
    assert len(set(stamps)) == 120


@pytest.fixture(scope="module")
def clickhouse(tmp_path_factory):
    store = ClickHouseStore(
        f"chdb://{tmp_path_factory.mktemp('exports') / 'ch'}", database="exports"
    )
    store.migrate()
    history(store)
    yield store
    store.close()


def test_csv_is_the_view_in_the_window(clickhouse) -> None:
    """CSV: the robot_poses header, only rows with from <= at < to, one robot if asked."""
    body = export_table(clickhouse, "robot-poses", "csv", T0 + 10_000, T0 + 20_000, "b").decode()
    rows = list(csv.DictReader(io.StringIO(body)))
    assert len(rows) == 10 and {r["robot_id"] for r in rows} == {"b"}
    assert list(rows[0])[:4] == ["robot_id", "at", "x_m", "y_m"] and float(rows[0]["y_m"]) == 3.0


def test_parquet_reads_back(clickhouse, tmp_path) -> None:
    """Parquet: a file ClickHouse (or pandas, Spark, DuckDB) reads back with the same rows."""
    body = export_table(clickhouse, "chunk-changes", "parquet", T0 - 60_000, T0 + 60_000)
    assert body[:4] == b"PAR1"
    path = tmp_path / "changes.parquet"
    path.write_bytes(body)
    got = clickhouse.client.query(
        f"SELECT robot_id, chunk_row, chunk_col FROM file('{path}', 'Parquet') ORDER BY at"
    ).result_rows
    assert got == [("a", 0, 0), ("a", 1, 2), ("b", 1, 2)]


def test_vda_5050_facts_export_as_tables(clickhouse) -> None:
    """A vehicle's states, errors and connection states, each in its own dataset, once per
    fact although the message came twice (a QoS 1 redelivery)."""
    from mapservice.core.events import decode
    from mapservice.core.intake import Intake
    from mapservice.ingest.router import Router
    from mapservice.settings import Settings
    from tests.fixtures import vda5050 as vda

    router = Router(Settings(), gateway_id="export-test")
    ts = T0 + 30_000
    for subtopic, msg in (
        (
            "state",
            vda.state(
                "2.1.0",
                "Acme",
                "001",
                ts,
                x=4.5,
                y=-2.0,
                errors=(("WARNING", "lowBattery", "charge me"),),
            ),
        ),
        ("connection", vda.connection("2.1.0", "Acme", "001", ts + 1000, "OFFLINE")),
    ):
        record = router.route(f"uagv/v2/Acme/001/{subtopic}", vda.encode(msg), ts + 2000, Intake())
        assert record.reason is None
        for _ in range(2):  # two inserts: two parts, folded by FINAL
            clickhouse.append([decode(record.value)])
    window = (T0, T0 + 60_000, "Acme:001")
    states = list(
        csv.DictReader(
            io.StringIO(export_table(clickhouse, "vehicle-states", "csv", *window).decode())
        )
    )
    assert [
        (r["manufacturer"], r["serial_number"], float(r["x"]), float(r["y"]), r["error_count"])
        for r in states
    ] == [("Acme", "001", 4.5, -2.0, "1")]
    errors = list(
        csv.DictReader(
            io.StringIO(export_table(clickhouse, "vehicle-errors", "csv", *window).decode())
        )
    )
    assert [(r["level"], r["type"], r["description"]) for r in errors] == [
        ("WARNING", "lowBattery", "charge me")
    ]
    connections = list(
        csv.DictReader(
            io.StringIO(export_table(clickhouse, "vehicle-connections", "csv", *window).decode())
        )
    )
    assert [r["state"] for r in connections] == ["OFFLINE"]
    assert export_table(clickhouse, "vehicle-errors", "parquet", *window)[:4] == b"PAR1"
