"""VDA 5050 ingest: every subtopic of every covered version accepted into the history's
events; every malformed message a dead letter with its reason."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from mapservice.core.events import (
    PoseReported,
    VdaConnectionReported,
    VdaError,
    VdaFactsheetReported,
    VdaStateReported,
    decode,
    decode_dead_letter,
)
from mapservice.core.intake import Intake
from mapservice.core.vda_ids import robot_id_for, vehicle_of
from mapservice.core.wire2019 import Reason
from mapservice.ingest.router import Router
from mapservice.ingest.vda5050 import SUBTOPICS, validator
from mapservice.settings import Settings
from tests.fixtures import vda5050 as vda

VERSIONS = ["2.0.0", "2.1.0", "3.0.0"]


def topic(
    version: str,
    subtopic: str,
    manufacturer: str = "Acme",
    serial: str = "001",
    interface: str = "uagv",
) -> str:
    return f"{interface}/v{version[0]}/{manufacturer}/{serial}/{subtopic}"


def message(version: str, subtopic: str, ms: int) -> dict:
    if subtopic == "connection":
        return vda.connection(version, "Acme", "001", ms, "ONLINE")
    return getattr(vda, subtopic)(version, "Acme", "001", ms)


@pytest.fixture
def router() -> Router:
    return Router(Settings(), gateway_id="gw-test")


def route(router: Router, version: str, subtopic: str, msg: dict, now_ms: int, **kw):
    return router.route(topic(version, subtopic, **kw), vda.encode(msg), now_ms, Intake())


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("subtopic", SUBTOPICS)
def test_every_subtopic_of_every_version_is_accepted(router, now_ms, version, subtopic) -> None:
    msg = message(version, subtopic, now_ms - 1000)
    assert not list(validator(version, subtopic).iter_errors(msg))  # the official schema's verdict
    record = route(router, version, subtopic, msg, now_ms)
    assert record.reason is None, decode_dead_letter(record.value).detail
    env = decode(record.value)
    assert env.robot_id == "Acme:001" and record.key == b"Acme:001"
    expected = {
        "state": VdaStateReported,
        "visualization": PoseReported,
        "connection": VdaConnectionReported,
        "factsheet": VdaFactsheetReported,
    }[subtopic]
    assert isinstance(env.payload, expected)
    settings = Settings()
    assert record.topic == (
        settings.topic_pose_events
        if subtopic in ("state", "visualization")
        else settings.topic_meta_events
    )


@pytest.mark.parametrize("version", VERSIONS)
def test_state_maps_pose_battery_loads_path_errors_and_status(router, now_ms, version) -> None:
    msg = vda.state(
        version,
        "Acme",
        "001",
        now_ms - 500,
        x=4.5,
        y=-2.0,
        theta=math.pi / 2,
        battery=42.5,
        charging=True,
        loads=[{"loadId": "L1"}],
        nodes=((5.0, 6.0), (7.0, 8.0)),
        paused=True,
        driving=False,
        errors=(("WARNING", "lowBattery", "below 50 %"), ("FATAL", "bumper", "")),
    )
    env = decode(route(router, version, "state", msg, now_ms).value)
    p = env.payload
    assert env.event_time_ms == now_ms - 500
    assert p.pose.position == (4.5, -2.0, 0.0)
    assert p.pose.orientation == pytest.approx((0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)))
    assert (p.pose.battery_level, p.pose.charging, p.pose.loaded) == (42.5, True, True)
    assert p.pose.path == ((5.0, 6.0), (7.0, 8.0))
    assert (p.driving, p.paused, p.operating_mode, p.order_id) == (
        False,
        True,
        "AUTOMATIC",
        "order-1",
    )
    assert p.errors == (
        VdaError("WARNING", "lowBattery", "below 50 %"),
        VdaError("FATAL", "bumper", ""),
    )
    assert (p.map_id, p.on_known_map, p.manufacturer, p.serial_number) == (
        "hall",
        True,
        "Acme",
        "001",
    )
    empty = vda.state(version, "Acme", "001", now_ms, loads=[])
    assert decode(route(router, version, "state", empty, now_ms).value).payload.pose.loaded is False


@pytest.mark.parametrize("version", VERSIONS)
def test_visualization_carries_the_last_state_forward(router, now_ms, version) -> None:
    first = decode(
        route(
            router,
            version,
            "visualization",
            vda.visualization(version, "Acme", "001", now_ms - 3000),
            now_ms,
        ).value
    )
    assert first.payload.battery_level is None  # no state yet: nothing to carry
    route(
        router,
        version,
        "state",
        vda.state(
            version,
            "Acme",
            "001",
            now_ms - 2000,
            battery=61.0,
            charging=True,
            loads=[{"loadId": "L"}],
        ),
        now_ms,
    )
    env = decode(
        route(
            router,
            version,
            "visualization",
            vda.visualization(version, "Acme", "001", now_ms - 1000, x=9.0, y=8.0, theta=0.0),
            now_ms,
        ).value
    )
    assert isinstance(env.payload, PoseReported)
    assert env.payload.position == (9.0, 8.0, 0.0)
    assert (env.payload.battery_level, env.payload.charging, env.payload.loaded) == (
        61.0,
        True,
        True,
    )
    assert env.payload.path == ((3.0, 4.0),)
    other = decode(
        route(
            router,
            version,
            "visualization",
            vda.visualization(version, "Acme", "002", now_ms),
            now_ms,
            serial="002",
        ).value
    )
    assert other.payload.battery_level is None  # per vehicle


def test_map_transforms_move_known_maps_and_flag_unknown_ones(now_ms) -> None:
    router = Router(Settings(vda5050_map_transforms={"hall": (10.0, 0.0, math.pi / 2)}), "gw")
    env = decode(
        route(
            router,
            "2.0.0",
            "state",
            vda.state("2.0.0", "Acme", "001", now_ms, x=1.0, y=0.0, theta=0.0, nodes=((2.0, 0.0),)),
            now_ms,
        ).value
    )
    assert env.payload.pose.position == pytest.approx((10.0, 1.0, 0.0))
    assert env.payload.pose.orientation == pytest.approx(
        (0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4))
    )
    assert len(env.payload.pose.path) == 1 and env.payload.pose.path[0] == pytest.approx(
        (10.0, 2.0)
    )
    assert (env.payload.x, env.payload.y) == (1.0, 0.0)  # as reported, in the vehicle's frame
    off = decode(
        route(
            router,
            "2.0.0",
            "state",
            vda.state("2.0.0", "Acme", "001", now_ms, x=1.0, y=0.0, map_id="cellar"),
            now_ms,
        ).value
    )
    assert off.payload.pose is None and off.payload.on_known_map is False
    assert (off.payload.map_id, off.payload.x) == ("cellar", 1.0)  # stored, flagged, not drawn
    viz = decode(
        route(
            router,
            "2.0.0",
            "visualization",
            vda.visualization("2.0.0", "Acme", "001", now_ms, map_id="cellar"),
            now_ms,
        ).value
    )
    assert isinstance(viz.payload, VdaStateReported) and viz.payload.on_known_map is False


def test_connection_broken_is_offline_when_received_not_when_composed(router, now_ms) -> None:
    connect_ms = now_ms - 60_000  # the last will carries the connect time
    env = decode(
        route(
            router,
            "2.0.0",
            "connection",
            vda.connection("2.0.0", "Acme", "001", connect_ms, "CONNECTIONBROKEN"),
            now_ms,
        ).value
    )
    assert (env.event_time_ms, env.payload.sent_time_ms, env.payload.state) == (
        now_ms,
        connect_ms,
        "CONNECTIONBROKEN",
    )
    online = decode(
        route(
            router,
            "2.0.0",
            "connection",
            vda.connection("2.0.0", "Acme", "001", connect_ms, "ONLINE"),
            now_ms,
        ).value
    )
    assert online.event_time_ms == connect_ms


def test_factsheet_is_kept_as_sent(router, now_ms) -> None:
    msg = vda.factsheet("2.1.0", "Acme", "001", now_ms)
    env = decode(route(router, "2.1.0", "factsheet", msg, now_ms).value)
    assert json.loads(env.payload.factsheet_json) == msg


def dead_letter(record) -> tuple[str, str]:
    assert record.reason is not None
    letter = decode_dead_letter(record.value)
    return letter.reason, letter.detail


def test_a_payload_naming_another_vehicle_is_refused(router, now_ms) -> None:
    msg = vda.state("2.0.0", "Acme", "002", now_ms)
    reason, detail = dead_letter(route(router, "2.0.0", "state", msg, now_ms))
    assert reason == Reason.ROBOT_ID_MISMATCH.value and "'002'" in detail
    msg = vda.state("2.0.0", "Other", "001", now_ms)
    assert dead_letter(route(router, "2.0.0", "state", msg, now_ms))[0] == "robot_id_mismatch"


@pytest.mark.parametrize(
    "raw_topic, payload, reason",
    [
        ("uagv/v2/Acme/001/order", b"{}", "unknown_topic"),
        ("uagv/v2/Acme/001/state/x", b"{}", "unknown_topic"),
        ("uagv/v2/Acme//state", b"{}", "unknown_topic"),
        ("uagv/v2/Acme/001/state", b"{not json", "not_json"),
        ("uagv/v2/Acme/001/state", b"[1, 2]", "wrong_type"),
        ("uagv/v2/Acme/001/state", b'{"version": "1.1.0"}', "vda_unsupported_version"),
        ("uagv/v3/Acme/001/state", b'{"version": "2.0.0"}', "vda_unsupported_version"),
        ("uagv/v2/Acme/001/state", b'{"version": 2}', "vda_unsupported_version"),
        # 2.0.0's visualization schema requires nothing: the header is still required.
        ("uagv/v2/Acme/001/visualization", b'{"version": "2.0.0"}', "missing_field"),
    ],
)
def test_malformed_messages_are_dead_lettered(router, now_ms, raw_topic, payload, reason) -> None:
    assert dead_letter(router.route(raw_topic, payload, now_ms, Intake()))[0] == reason


def test_bad_timestamps_and_overlong_ids_are_dead_lettered(router, now_ms) -> None:
    msg = vda.state("2.0.0", "Acme", "001", now_ms + 3_600_000)
    assert dead_letter(route(router, "2.0.0", "state", msg, now_ms))[0] == "timestamp_in_future"
    long = "M" * 40
    msg = vda.state("2.0.0", long, long, now_ms)
    reason, detail = dead_letter(
        route(router, "2.0.0", "state", msg, now_ms, manufacturer=long, serial=long)
    )
    assert reason == "bad_robot_id" and "64" in detail
    viz = vda.visualization("2.0.0", "Acme", "001", now_ms)
    del viz["agvPosition"]
    assert dead_letter(route(router, "2.0.0", "visualization", viz, now_ms))[0] == "vda_no_position"


def invalid_variants(version: str, subtopic: str, msg: dict):
    """Each required property left out, and each property given a value of a wrong type."""
    schema = validator(version, subtopic).schema
    for key in schema.get("required", ()):
        if key in msg and key != "version":  # without a version: vda_unsupported_version
            yield f"without {key}", {k: v for k, v in msg.items() if k != key}
    for key, value in msg.items():
        if key in ("version", "manufacturer", "serialNumber") or key not in schema.get(
            "properties", {}
        ):
            continue  # checked before the schema (version) or against the topic; untyped
        wrong = {"bad": [value]} if not isinstance(value, dict) else "not an object"
        yield f"{key} of a wrong type", msg | {key: wrong}


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("subtopic", SUBTOPICS)
def test_generated_invalid_messages_are_dead_lettered_with_the_schema_reason(
    router, now_ms, version, subtopic
) -> None:
    msg = message(version, subtopic, now_ms)
    variants = list(invalid_variants(version, subtopic, msg))
    assert len(variants) >= 3
    for name, bad in variants:
        reason, detail = dead_letter(route(router, version, subtopic, bad, now_ms))
        assert reason == "vda_schema", name
        assert f"VDA 5050 {version} {subtopic}" in detail, detail


@given(st.text(min_size=1, max_size=8), st.text(min_size=1, max_size=8))
@hsettings(max_examples=300)
def test_robot_ids_are_reversible_and_within_the_rules(manufacturer, serial) -> None:
    from mapservice.core.wire2019 import _ROBOT_ID

    robot_id = robot_id_for(manufacturer, serial)
    assert vehicle_of(robot_id) == (manufacturer, serial)
    if len(robot_id) <= 64:
        assert _ROBOT_ID.fullmatch(robot_id)
    assert robot_id_for("Acme", "001") == "Acme:001"
    assert vehicle_of("plain-2019-robot") is None


def test_the_interface_name_is_a_setting(now_ms) -> None:
    settings = Settings(vda5050_interface="agv")
    assert {
        "agv/+/+/+/state",
        "agv/+/+/+/visualization",
        "agv/+/+/+/connection",
        "agv/+/+/+/factsheet",
    } <= set(settings.mqtt_subscriptions)
    # master control's orders and instant actions share the subtree: not subscribed
    assert not any(
        t.startswith("agv/")
        and not t.endswith(("/state", "/visualization", "/connection", "/factsheet"))
        for t in settings.mqtt_subscriptions
    )
    router = Router(settings, "gw")
    msg = vda.state("2.0.0", "Acme", "001", now_ms)
    assert route(router, "2.0.0", "state", msg, now_ms, interface="agv").reason is None
    assert dead_letter(route(router, "2.0.0", "state", msg, now_ms))[0] == "unknown_topic"
    off = Router(Settings(vda5050_interface=""), "gw")
    assert not any(t.startswith("uagv") for t in Settings(vda5050_interface="").mqtt_subscriptions)
    assert (
        dead_letter(route(off, "2.0.0", "state", msg, now_ms, interface="agv"))[0]
        == "unknown_topic"
    )


@pytest.mark.parametrize("version", ["2.0.0", "2.1.0"])
def test_a_node_state_without_theta_is_accepted(router, now_ms, version) -> None:
    """An order's nodePosition may omit theta and a vehicle echoes it in its nodeStates
    (npm vda-5050-lib does); 2.0.0's state schema alone requires it there (an erratum
    fixed in 2.1.0). Anything else missing from a nodePosition is still refused."""
    msg = vda.state(version, "Acme", "001", now_ms)
    del msg["nodeStates"][0]["nodePosition"]["theta"]
    assert route(router, version, "state", msg, now_ms).reason is None
    del msg["nodeStates"][0]["nodePosition"]["mapId"]
    reason, detail = dead_letter(route(router, version, "state", msg, now_ms))
    assert reason == "vda_schema" and "nodeStates/0/nodePosition" in detail


@pytest.mark.parametrize("subtopic", ["state", "visualization", "factsheet"])
def test_nan_and_infinity_tokens_are_not_json(router, now_ms, subtopic) -> None:
    msg = message("2.0.0", subtopic, now_ms)
    msg["headerId"] = float("nan")  # json.dumps writes the token NaN, which JSON lacks
    payload = json.dumps(msg).encode()
    assert b"NaN" in payload
    letter = dead_letter(router.route(topic("2.0.0", subtopic), payload, now_ms, Intake()))
    assert letter == ("not_json", "not JSON: NaN is not a JSON number")
    payload = json.dumps(msg).replace("NaN", "-Infinity").encode()
    letter = dead_letter(router.route(topic("2.0.0", subtopic), payload, now_ms, Intake()))
    assert letter[0] == "not_json" and "-Infinity" in letter[1]


@pytest.mark.parametrize(
    "subtopic, where, value",
    [
        ("visualization", ("agvPosition", "x"), "1e400"),
        ("visualization", ("agvPosition", "y"), str(10**400)),
        ("visualization", ("agvPosition", "x"), "2e6"),
        ("state", ("agvPosition", "theta"), "-1e400"),
        ("state", ("batteryState", "batteryCharge"), "1e400"),
        ("state", ("nodeStates", 0, "nodePosition", "x"), "1e400"),
    ],
)
def test_numbers_beyond_a_float_or_the_floor_are_out_of_range(
    router, now_ms, subtopic, where, value
) -> None:
    msg = message("2.0.0", subtopic, now_ms)
    if where[0] == "nodeStates":
        assert msg["nodeStates"] and "nodePosition" in msg["nodeStates"][0]
    target = msg
    for key in where[:-1]:
        target = target[key]
    marker = 123456.789
    target[where[-1]] = marker
    payload = json.dumps(msg).replace(repr(marker), value).encode()
    reason, detail = dead_letter(router.route(topic("2.0.0", subtopic), payload, now_ms, Intake()))
    assert reason == "out_of_range" and "finite" in detail
    # The same message with an ordinary number is stored.
    payload = json.dumps(msg).replace(repr(marker), "1.5").encode()
    assert router.route(topic("2.0.0", subtopic), payload, now_ms, Intake()).reason is None
