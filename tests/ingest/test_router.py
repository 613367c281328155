"""The pure router: MQTT topic + payload to a Kafka record (event or dead letter)."""

from __future__ import annotations

import pytest

from mapservice.core.events import ChunkUpdated, PoseReported, decode, decode_dead_letter
from mapservice.core.intake import Intake
from mapservice.core.wire2019 import Limits, Reason
from mapservice.ingest.router import Router
from mapservice.settings import Settings


@pytest.fixture
def settings() -> Settings:
    return Settings()


@pytest.fixture
def router(settings: Settings) -> Router:
    return Router(settings, gateway_id="gw-test")


def test_chunk_goes_to_chunk_topic_keyed_by_cell(router, settings, wire, now_ms) -> None:
    """An accepted chunk becomes a ChunkUpdated on the chunk topic, keyed `row:column`."""
    record = router.route("iot/chunks/create", wire.chunk(row=7, column=11), now_ms, Intake())
    assert record.reason is None
    assert record.topic == settings.topic_chunk_events == "mapservice.chunk-events.v1"
    assert record.key == b"7:11"
    env = decode(record.value)
    assert env == record.envelope
    assert isinstance(env.payload, ChunkUpdated) and (env.payload.row, env.payload.column) == (
        7,
        11,
    )
    assert env.receive_time_ms == now_ms


def test_pose_goes_to_pose_topic_keyed_by_robot(router, settings, wire, now_ms) -> None:
    """An accepted pose becomes a PoseReported on the pose topic, keyed by robot id."""
    record = router.route("iot/coordinates/blabla", wire.pose(), now_ms, Intake())
    assert record.reason is None
    assert record.topic == settings.topic_pose_events
    assert record.key == b"blabla"
    env = decode(record.value)
    assert isinstance(env.payload, PoseReported) and env.robot_id == "blabla"


@pytest.mark.parametrize(
    "topic",
    [
        "iot/chunks/delete",
        "iot/chunks/create/a/b",
        "iot/coordinates",
        "other/coordinates/blabla",
        "",
    ],
)
def test_unknown_topic_is_dead_lettered(router, settings, wire, now_ms, topic) -> None:
    """A topic without a handler gives an unknown_topic dead letter with the original bytes."""
    payload = wire.pose()
    record = router.route(topic, payload, now_ms, Intake())
    assert record.reason == Reason.UNKNOWN_TOPIC.value == "unknown_topic"
    assert record.topic == settings.topic_dead_letter
    assert record.envelope is None
    letter = decode_dead_letter(record.value)
    assert (letter.reason, letter.mqtt_topic, letter.payload) == ("unknown_topic", topic, payload)


def test_rejection_is_dead_lettered_with_everything(router, settings, now_ms) -> None:
    """A rejected message keeps reason, detail, original bytes, MQTT topic, time and gateway."""
    payload = b'{"row": 3, "column": 2, oops'
    record = router.route("iot/chunks/create", payload, now_ms, Intake())
    assert record.reason == "not_json"
    assert record.topic == settings.topic_dead_letter == "mapservice.dead-letter.v1"
    assert record.key == b"iot/chunks/create"
    letter = decode_dead_letter(record.value)
    assert letter.reason == "not_json"
    assert "not JSON" in letter.detail
    assert letter.payload == payload
    assert letter.mqtt_topic == "iot/chunks/create"
    assert letter.receive_time_ms == now_ms
    assert letter.gateway == "gw-test"


def test_topic_robot_id_must_match_payload(router, wire, now_ms) -> None:
    """The robot named by the coordinates topic must be the payload's robotId."""
    record = router.route("iot/coordinates/robot-2", wire.pose(), now_ms, Intake())
    assert record.reason == "robot_id_mismatch"
    assert decode_dead_letter(record.value).mqtt_topic == "iot/coordinates/robot-2"


def test_limits_passed_in_are_applied(router, wire, now_ms) -> None:
    """The limits given to route() decide what is in the map."""
    narrow = Intake(Limits(chunk_rows=2, chunk_cols=2))
    assert (
        router.route("iot/chunks/create", wire.chunk(row=1, column=1), now_ms, narrow).reason
        is None
    )
    assert (
        router.route("iot/chunks/create", wire.chunk(row=2, column=1), now_ms, narrow).reason
        == "out_of_map"
    )


def test_configured_topics_are_used(wire, now_ms) -> None:
    """Custom MQTT and Kafka topic names from the settings are honoured."""
    s = Settings(
        create_chunk_topic="site1/chunks",
        coordinate_topic="site1/robots/#",
        topic_chunk_events="c",
        topic_pose_events="p",
        topic_dead_letter="d",
    )
    r = Router(s, "gw")
    assert r.route("site1/chunks", wire.chunk(), now_ms, Intake()).topic == "c"
    assert r.route("site1/robots/blabla", wire.pose(), now_ms, Intake()).topic == "p"
    assert r.route("iot/chunks/create", wire.chunk(), now_ms, Intake()).topic == "d"


def test_robot_chunk_topic_names_the_robot(router, settings, wire, now_ms) -> None:
    """A chunk on iot/chunks/create/<robotId> is the same ChunkUpdated the 2019 topic gives,
    attributed to that robot; a payload naming another robot is a robot_id_mismatch dead letter."""
    legacy = router.route(
        "iot/chunks/create", wire.chunk(row=7, column=11, robotId="r1"), now_ms, Intake()
    )
    own = router.route(
        "iot/chunks/create/r1", wire.chunk(row=7, column=11, robotId="r1"), now_ms, Intake()
    )
    assert own.reason is None and (own.topic, own.key, own.value) == (
        legacy.topic,
        legacy.key,
        legacy.value,
    )
    assert own.envelope.robot_id == "r1"
    other = router.route("iot/chunks/create/r1", wire.chunk(robotId="r2"), now_ms, Intake())
    assert other.reason == "robot_id_mismatch" and other.topic == settings.topic_dead_letter
    letter = decode_dead_letter(other.value)
    assert "'r1'" in letter.detail and "'r2'" in letter.detail
    assert letter.mqtt_topic == "iot/chunks/create/r1"


def test_robot_chunk_topic_can_be_configured_or_turned_off(wire, now_ms) -> None:
    """MAPSERVICE_ROBOT_CHUNK_TOPIC moves the per-robot chunk topic; empty turns it off (and
    an empty MAPSERVICE_CREATE_CHUNK_TOPIC the 2019 one): such messages are unknown_topic."""
    moved = Router(Settings(robot_chunk_topic="site1/chunks/+"), "gw")
    assert moved.route("site1/chunks/r1", wire.chunk(robotId="r1"), now_ms, Intake()).reason is None
    off = Router(Settings(robot_chunk_topic="", create_chunk_topic=""), "gw")
    for topic in ("iot/chunks/create/r1", "iot/chunks/create"):
        assert (
            off.route(topic, wire.chunk(robotId="r1"), now_ms, Intake()).reason == "unknown_topic"
        )
    assert Settings(robot_chunk_topic="", create_chunk_topic="").mqtt_subscriptions == [
        "iot/coordinates/#",
        "uagv/+/+/+/state",
        "uagv/+/+/+/visualization",
        "uagv/+/+/+/connection",
        "uagv/+/+/+/factsheet",
        "iot/robots/+/command-events",
    ]


@pytest.mark.parametrize(
    "filter_", ["iot/coordinates/#", "iot/coordinates/+", "iot/coordinates/", "iot/coordinates"]
)
def test_coordinate_topic_filter_forms(filter_, wire, now_ms) -> None:
    """Whether configured as `.../#`, `.../+` or a bare prefix, iot/coordinates/<id> is routed."""
    r = Router(Settings(coordinate_topic=filter_), "gw")
    record = r.route("iot/coordinates/blabla", wire.pose(), now_ms, Intake())
    assert record.reason is None, decode_dead_letter(record.value).detail
