"""The analysts' views against a brute-force computation on small data, and the schema's
comments: every table, view and column an analyst sees is described."""

from __future__ import annotations

import math
import random
import time

import pytest

from mapservice.adapters.clickhouse.analyst_views import LATER_VIEWS, VIEWS
from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.clickhouse.table_comments import LATER_TABLE_COMMENTS, TABLE_COMMENTS
from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationRemoved,
    Zone,
    ZoneViolation,
)
from mapservice.core.events import PoseReported, make_envelope
from mapservice.core.intake import Intake
from mapservice.core.ports import ConflictRow
from mapservice.core.wire2019 import content_hash
from robot.chunks import metres_to_pixel
from tests.conftest import chunk_event, dead_letter, meta_event

T0 = (time.time_ns() // 1_000_000 // 60_000) * 60_000 - 3_600_000  # a whole minute, an hour ago


def yaw_quaternion(deg: float) -> tuple[float, float, float, float]:
    half = math.radians(deg) / 2
    return (0.0, 0.0, math.sin(half), math.cos(half))


@pytest.fixture(scope="module")
def loaded(tmp_path_factory):
    """A store with 3 robots' random walks over 5 minutes, flags of every kind, chunk writes,
    conflicts and dead letters; and the poses as written (the brute force's input)."""
    store = ClickHouseStore(f"chdb://{tmp_path_factory.mktemp('views') / 'ch'}", database="views")
    store.migrate()
    rng = random.Random(7)
    meta = meta_event(T0 - 1000)
    poses = []
    flags = [True, False, None, "yes"]
    for robot in ("r1", "r2", "r3"):
        x, y = 2.0, 4.0
        for i in range(0, 300, 2):
            x, y = x + rng.uniform(-0.4, 0.6), y + rng.uniform(-0.3, 0.3)
            heading = rng.uniform(-179, 179)
            payload = PoseReported(
                position=(x, y, 0.0),
                orientation=yaw_quaternion(heading),
                battery_level=round(90 - i / 10, 1),
                charging=flags[i % 4],
                loaded=flags[(i // 2) % 4],
            )
            lag = rng.randint(-2000, 8000)
            poses.append((robot, T0 + i * 1000, x, y, heading, payload, lag))
    store.append([meta] + [make_envelope(r, t, t + lag, p) for r, t, _, _, _, p, lag in poses])
    store.append(
        [
            chunk_event("r1", T0 + 5000, 1, 2),
            chunk_event("r2", T0 + 9000, 1, 2, bytes([9]) * 10_000),
            chunk_event("r3", T0 + 70_000, 0, 0),
        ]
    )
    store.append_conflicts([ConflictRow(1, 2, T0 + 9000, "r1", T0 + 5000, "r2")])
    store.append_dead_letters([dead_letter("too_deep", b"[" * 2048, T0), dead_letter("not_json")])
    yield store, poses, meta.payload
    store.close()


def rows(store, sql: str) -> list[dict]:
    result = store.client.query(sql)
    return [dict(zip(result.column_names, row)) for row in result.result_rows]


def test_robot_poses_are_metres_degrees_flags_and_chunks(loaded) -> None:
    """robot_poses: positions in metres, yaw in degrees, JSON booleans as Bool, chunk cells."""
    store, poses, meta = loaded
    got = {
        (r["robot_id"], r["at"].timestamp() * 1000): r
        for r in rows(store, "SELECT * FROM views.robot_poses")
    }
    assert len(got) == len(poses)
    as_bool = {True: True, False: False, None: None, "yes": None}
    for robot, t, x, y, heading, payload, lag in poses:
        row = got[(robot, float(t))]
        assert row["x_m"] == pytest.approx(x, abs=0.0011) and row["y_m"] == pytest.approx(
            y, abs=0.0011
        )
        assert row["heading_deg"] == pytest.approx(heading, abs=0.01)
        assert (
            row["charging"] is as_bool[payload.charging]
            and row["loaded"] is as_bool[payload.loaded]
        )
        assert row["receive_lag_s"] == pytest.approx(lag / 1000)
        col, pixel_row = metres_to_pixel(row["x_m"], row["y_m"], meta)
        assert (row["chunk_row"], row["chunk_col"]) == (
            pixel_row // meta.chunk_height,
            col // meta.chunk_width,
        )


def test_robot_minutes_match_brute_force(loaded) -> None:
    """robot_minutes: reports, distance (steps between consecutive reports) and battery per minute."""
    store, poses, _ = loaded
    expected: dict[tuple[str, int], dict] = {}
    last: dict[str, tuple[float, float]] = {}
    for robot, t, x, y, _, payload, _ in sorted(poses, key=lambda p: (p[0], p[1])):
        mm = round(x * 1000) / 1000, round(y * 1000) / 1000  # as stored
        px, py = last.get(robot, mm)
        last[robot] = mm
        cell = expected.setdefault(
            (robot, t // 60_000 * 60_000), {"poses": 0, "distance": 0.0, "battery": []}
        )
        cell["poses"] += 1
        cell["distance"] += math.hypot(mm[0] - px, mm[1] - py)
        cell["battery"].append(payload.battery_level)
    got = rows(store, "SELECT * FROM views.robot_minutes")
    assert len(got) == len(expected)
    for row in got:
        cell = expected[(row["robot_id"], int(row["minute"].timestamp()) * 1000)]
        assert row["poses"] == cell["poses"]
        assert row["distance_m"] == pytest.approx(cell["distance"], abs=0.002)
        assert row["battery_level_min"] == pytest.approx(min(cell["battery"]), abs=1e-4)


def test_chunk_changes_and_conflicts_read_cleanly(loaded) -> None:
    """chunk_changes: one row per write with its MD5 in hex; chunk_conflicts: the pair and the gap."""
    store, _, _ = loaded
    changes = rows(store, "SELECT * FROM views.chunk_changes ORDER BY at")
    assert [(c["robot_id"], c["chunk_row"], c["chunk_col"]) for c in changes] == [
        ("r1", 1, 2),
        ("r2", 1, 2),
        ("r3", 0, 0),
    ]
    assert changes[0]["content_hash"] == content_hash(bytes(100 * 100)).hex()
    (conflict,) = rows(store, "SELECT * FROM views.chunk_conflicts")
    assert (conflict["robot_id"], conflict["other_robot_id"], conflict["seconds_apart"]) == (
        "r2",
        "r1",
        4.0,
    )


def test_dead_letter_messages_have_reason_and_size(loaded) -> None:
    """dead_letter_messages: the reason and the stored payload's size."""
    store, _, _ = loaded
    got = sorted(
        (r["reason"], r["payload_bytes"])
        for r in rows(store, "SELECT * FROM views.dead_letter_messages")
    )
    assert got == [("not_json", 5), ("too_deep", 2048)]


def test_keep_out_violations_name_the_zone_as_it_stood(loaded) -> None:
    """keep_out_violations: each stored violation with the zone's name and who drew it as it
    stood at the pose's time (a renamed zone: the old name before, the new one after)."""
    store, _, _ = loaded
    square = ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0))
    store.append(
        [
            make_envelope(
                "op", T0, T0, AnnotationCreated("z1", "op-anna", Zone("dock", "keep_out", square))
            ),
            make_envelope(
                "op",
                T0 + 60_000,
                T0 + 60_000,
                AnnotationChanged("z1", "op-ben", Zone("dock (wet floor)", "keep_out", square)),
            ),
            make_envelope("op", T0 + 90_000, T0 + 90_000, AnnotationRemoved("z1", "op-ben")),
        ]
    )
    store.append_zone_violations(
        [
            ZoneViolation(T0 + 10_000, "r1", "z1", 1.0, 1.5),
            ZoneViolation(T0 + 70_000, "r2", "z1", 0.5, 0.5),
        ]
    )
    got = rows(store, "SELECT * FROM views.keep_out_violations ORDER BY at")
    assert [
        (r["robot_id"], r["zone_id"], r["zone_name"], r["zone_drawn_by"], r["x_m"], r["y_m"])
        for r in got
    ] == [
        ("r1", "z1", "dock", "op-anna", 1.0, 1.5),
        ("r2", "z1", "dock (wet floor)", "op-ben", 0.5, 0.5),
    ]
    assert int(got[1]["zone_drawn_at"].timestamp() * 1000) == T0 + 60_000


def test_every_table_view_and_column_has_a_comment(loaded) -> None:
    """system.tables/system.columns: nothing the analyst sees is undescribed."""
    store, _, _ = loaded
    tables = rows(
        store,
        "SELECT name, comment FROM system.tables WHERE database = 'views' "
        "AND name NOT LIKE '%_mv' AND NOT is_temporary",
    )
    assert {t["name"] for t in tables} == (
        set(TABLE_COMMENTS) | set(LATER_TABLE_COMMENTS) | set(VIEWS) | set(LATER_VIEWS)
    )
    assert all(t["comment"] for t in tables)
    undocumented = rows(
        store,
        "SELECT table, name FROM system.columns WHERE database = 'views' "
        "AND comment = '' AND table IN ({})".format(
            ", ".join(f"'{t}'" for t in {**TABLE_COMMENTS, **LATER_TABLE_COMMENTS})
        ),
    )
    # pose_keyframes and pose_derivations repeat the poses columns (described there); only
    # pose_keyframes' own are commented.
    assert {
        (r["table"], r["name"])
        for r in undocumented
        if r["table"] not in ("pose_keyframes", "pose_derivations")
    } == set()
    for view, (_, _, columns) in {**VIEWS, **LATER_VIEWS}.items():
        described = [r["name"] for r in rows(store, f"DESCRIBE TABLE views.{view}")]
        assert described == list(columns), view


def test_the_guide_holds_the_schemas_reference() -> None:
    """docs/analysts.md's reference is what the schema says (regenerate: python -m mapservice.adapters.clickhouse.analyst_schema)."""
    from mapservice.adapters.clickhouse.analyst_schema import reference_markdown
    from tests.fixtures.paths import ROOT

    guide = (ROOT / "docs" / "analysts.md").read_text()
    assert reference_markdown() in guide


def test_vehicle_views_read_vda_5050_facts(loaded) -> None:
    """vehicle_states, vehicle_errors, vehicle_connections (spans until the next state) and
    vehicle_factsheets (the main facts as columns) over VDA 5050 messages as ingested. The
    vehicle is on a map id without a transform: its facts are stored, no pose is drawn (the
    other tests' robots stay the only ones in robot_poses)."""
    from mapservice.core.events import decode
    from mapservice.ingest.router import Router
    from mapservice.settings import Settings
    from tests.fixtures import vda5050 as vda

    store, _, _ = loaded
    router = Router(Settings(vda5050_map_transforms={"hall": (0.0, 0.0, 0.0)}), "gw")
    v, m, s = "2.1.0", "Acme Co", "7"  # (2.0.0's official factsheet schema nests nothing)
    sheet = vda.factsheet(v, m, s, T0)
    sheet["typeSpecification"].update(seriesName="Tugger 3", agvClass="TUGGER", maxLoadMass=450)
    sheet["physicalParameters"].update(speedMax=1.8, length=1.2, width=0.6)
    messages = [
        ("connection", vda.connection(v, m, s, T0, "ONLINE"), T0),
        ("factsheet", sheet, T0),
        (
            "state",
            vda.state(
                v,
                m,
                s,
                T0 + 1000,
                x=1.5,
                y=2.5,
                theta=math.pi / 2,
                map_id="cellar",
                paused=True,
                driving=False,
                errors=(("WARNING", "lowBattery", "charge me"), ("FATAL", "bumper", "hit")),
            ),
            T0 + 1000,
        ),
        ("connection", vda.connection(v, m, s, T0, "CONNECTIONBROKEN"), T0 + 5000),
    ]
    events = []
    for subtopic, msg, received in messages:
        record = router.route(f"uagv/v2/{m}/{s}/{subtopic}", vda.encode(msg), received, Intake())
        assert record.reason is None, record.value
        events.append(decode(record.value))
    store.append(events)
    robot = "Acme@20Co:7"
    (state,) = rows(store, f"SELECT * FROM views.vehicle_states WHERE robot_id = '{robot}'")
    assert (
        state["manufacturer"],
        state["serial_number"],
        state["map_id"],
        state["on_known_map"],
    ) == (m, s, "cellar", False)
    assert (state["x_m"], state["y_m"], state["heading_deg"]) == (1.5, 2.5, 90.0)
    assert (state["driving"], state["paused"], state["operating_mode"], state["error_count"]) == (
        False,
        True,
        "AUTOMATIC",
        2,
    )
    errors = rows(
        store,
        "SELECT error_type, level, description, is_warning, toUnixTimestamp64Milli(at) AS t "
        f"FROM views.vehicle_errors WHERE robot_id = '{robot}' ORDER BY error_type",
    )
    assert [tuple(e.values()) for e in errors] == [
        ("bumper", "FATAL", "hit", False, T0 + 1000),
        ("lowBattery", "WARNING", "charge me", True, T0 + 1000),
    ]
    spans = rows(
        store,
        "SELECT state, online, toUnixTimestamp64Milli(at) AS a, toUnixTimestamp64Milli(until) "
        f"AS u, duration_s FROM views.vehicle_connections WHERE robot_id = '{robot}' ORDER BY at",
    )
    assert [tuple(r.values()) for r in spans] == [
        ("ONLINE", True, T0, T0 + 5000, 5.0),
        ("CONNECTIONBROKEN", False, T0 + 5000, None, None),
    ]
    (fact,) = rows(store, f"SELECT * FROM views.vehicle_factsheets WHERE robot_id = '{robot}'")
    assert (
        fact["manufacturer"],
        fact["serial_number"],
        fact["series_name"],
        fact["vehicle_class"],
    ) == (m, s, "Tugger 3", "TUGGER")
    assert (fact["speed_max_m_s"], fact["max_load_kg"], fact["length_m"], fact["width_m"]) == (
        1.8,
        450.0,
        1.2,
        0.6,
    )
    assert rows(
        store, f"SELECT count() AS n FROM views.robot_poses WHERE robot_id = '{robot}'"
    ) == [{"n": 0}]
