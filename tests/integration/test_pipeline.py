"""MQTT in, ClickHouse out, through real brokers: counts, dead letters, gateway crashes."""

from __future__ import annotations

import base64
import os
import signal
import threading
import time
import zlib

import httpx
import pytest

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.events import decode_dead_letter
from mapservice.core.wire2019 import encode_chunk_create, encode_coordinates, format_timestamp
from mapservice.ingest.router import DEAD_LETTER_PAYLOAD_MAX
from mapservice.robot.loadgen import RobotFleet
from tests.fixtures.paths import MAPS

from .conftest import merge_threads_lowered, read_topic, wait_for_count


def now_ms() -> int:
    return time.time_ns() // 1_000_000


def publish_all(stack, messages: list[tuple[str, bytes]]) -> None:
    host, port, _ = parse_mqtt_url(stack.mqtt_url)
    client = make_client(f"test-pub-{now_ms()}")
    client.connect(host, port)
    client.loop_start()
    try:
        infos = [client.publish(topic, payload, qos=1) for topic, payload in messages]
        for info in infos:
            info.wait_for_publish(30)
            assert info.is_published()
    finally:
        client.loop_stop()
        client.disconnect()


def pose_and_chunk_messages(prefix: str, robots: int, per_robot: int, start_ms: int):
    poses, chunks = [], []
    pixels = bytes(range(100)) * 100
    for r in range(robots):
        robot = f"{prefix}-{r}"
        for k in range(per_robot):
            ts = format_timestamp(start_ms + k * 1000 + r)
            poses.append(
                (
                    f"iot/coordinates/{robot}",
                    encode_coordinates(robot, ts, 1.0 + k, 2.0 + r, battery_level=50.0),
                )
            )
            if k % 5 == 0:
                chunks.append(
                    ("iot/chunks/create", encode_chunk_create(r % 3, k % 6, pixels, ts, robot))
                )
    return poses, chunks


@pytest.mark.parametrize("broker", ["mosquitto_stack", "amqtt_stack"])
def test_n_messages_arrive_exactly_n_times(broker, request):
    """N poses and M chunks published with paho appear in ClickHouse exactly once each."""
    stack = request.getfixturevalue(broker)
    prefix = f"exact{broker[:4]}"
    start = now_ms() - 60_000
    poses, chunks = pose_and_chunk_messages(prefix, robots=10, per_robot=50, start_ms=start)
    publish_all(stack, poses + chunks)
    stored_poses = wait_for_count(stack, "pose", prefix, start, start + 120_000, len(poses))
    stored_chunks = wait_for_count(stack, "chunk", prefix, start, start + 120_000, len(chunks))
    assert len(stored_poses) == len(poses) == len(set(stored_poses))
    assert len(stored_chunks) == len(chunks) == len(set(stored_chunks))


def test_republished_messages_are_stored_once(mosquitto_stack):
    """Publishing the very same messages twice (a QoS 1 redelivery) leaves one row each."""
    prefix = "redeliver"
    start = now_ms() - 30_000
    poses, chunks = pose_and_chunk_messages(prefix, robots=3, per_robot=10, start_ms=start)
    publish_all(mosquitto_stack, poses + chunks)
    publish_all(mosquitto_stack, poses + chunks)
    time.sleep(1.5)
    stored = wait_for_count(mosquitto_stack, "pose", prefix, start, start + 60_000, len(poses))
    assert sorted(stored) == sorted(set(stored)) and len(stored) == len(poses)


def bad_messages(ts: str) -> dict[str, tuple[str, bytes]]:
    """One message per bad-input class, keyed by the reason the gateway must give."""
    good_pose = encode_coordinates("bad-1", ts, 1, 2).decode()

    def chunk(**kw):
        return (
            "iot/chunks/create",
            httpx.Request(
                "POST",
                "http://x",
                json={
                    "pgmB64compressedData": base64.b64encode(zlib.compress(bytes(10000))).decode(),
                    "row": 0,
                    "column": 0,
                    "timestamp": ts,
                    "robotId": "bad-1",
                    **kw,
                },
            ).content,
        )

    return {
        "not_json": ("iot/coordinates/bad-1", b"{not json"),
        "missing_field": (
            "iot/coordinates/bad-1",
            good_pose.replace('"timestamp"', '"when"').encode(),
        ),
        "wrong_type": chunk(row="three"),
        "bad_robot_id": chunk(robotId="robot with spaces"),
        "bad_base64": chunk(pgmB64compressedData="%%%not-base64%%%"),
        "bad_zlib": chunk(pgmB64compressedData=base64.b64encode(b"not zlib at all").decode()),
        "wrong_chunk_size": chunk(
            pgmB64compressedData=base64.b64encode(zlib.compress(bytes(99))).decode()
        ),
        "out_of_map": chunk(row=999),
        "bad_timestamp": chunk(timestamp="yesterday at noon"),
        "timestamp_in_future": chunk(timestamp="2099-01-01T00:00:00"),
        "timestamp_too_old": chunk(timestamp="2018-12-20T23:34:33"),
        "robot_id_mismatch": ("iot/coordinates/someone-else", good_pose.encode()),
        "oversized": ("iot/coordinates/bad-1", b" " * 300_000 + good_pose.encode()),
    }


def test_every_bad_input_class_is_dead_lettered_with_its_reason(mosquitto_stack):
    """Each bad message lands in the dead-letter topic with its reason; good ones around it arrive."""
    stack = mosquitto_stack
    start = now_ms() - 20_000
    bad = bad_messages(format_timestamp(start))
    good, _ = pose_and_chunk_messages("amid-bad", robots=1, per_robot=len(bad) + 1, start_ms=start)
    interleaved = []
    for message, good_message in zip(bad.values(), good):
        interleaved += [good_message, message]
    interleaved.append(good[-1])
    publish_all(stack, interleaved)

    letters = [
        decode_dead_letter(v)
        for v in read_topic(stack, stack.settings().topic_dead_letter, min_records=len(bad))
    ]
    by_reason = {}
    for letter in letters:
        by_reason.setdefault(letter.reason, letter)
    assert set(bad) <= set(by_reason), f"missing reasons: {set(bad) - set(by_reason)}"
    for reason, (topic, payload) in bad.items():
        assert by_reason[reason].mqtt_topic == topic
        # Dead letters keep at most DEAD_LETTER_PAYLOAD_MAX bytes of a message (they must fit
        # in a Kafka record); the size and hash of the whole are in the detail.
        assert by_reason[reason].payload == payload[:DEAD_LETTER_PAYLOAD_MAX]
        if len(payload) > DEAD_LETTER_PAYLOAD_MAX:
            assert str(len(payload)) in by_reason[reason].detail
        assert by_reason[reason].detail
    stored = wait_for_count(stack, "pose", "amid-bad", start, start + 60_000, len(good))
    assert len(stored) == len(good)
    stats = httpx.get(f"{stack.api_url}/api/v1/stats").json()
    assert stats["dead_letters"] >= len(bad)


def test_gateway_sigkill_under_load_loses_and_duplicates_nothing(mosquitto_stack):
    """SIGKILL of the gateway mid-load, then restart: every published message stored exactly once."""
    stack = mosquitto_stack
    fleet = RobotFleet(
        stack.mqtt_url,
        load_ros_map(MAPS / "depot.yaml"),
        robots=100,
        prefix="kill",
        record=True,
        seed=11,
    )
    start = now_ms() - 1000
    runner = threading.Thread(target=fleet.run, args=(10.0,))
    runner.start()
    time.sleep(4.0)
    gateway = stack.procs["gateway"]
    os.kill(gateway.pid, signal.SIGKILL)
    gateway.wait()
    time.sleep(1.0)
    stack.start_gateway()
    runner.join(60)
    published_poses = {(r, ts) for kind, r, ts, _ in fleet.stats.published if kind == "pose"}
    published_chunks = {(r, ts) for kind, r, ts, _ in fleet.stats.published if kind == "chunk"}
    end = now_ms() + 1000
    poses = wait_for_count(stack, "pose", "kill", start, end, len(published_poses), timeout_s=90)
    chunks = wait_for_count(stack, "chunk", "kill", start, end, len(published_chunks), timeout_s=90)
    assert len(published_poses) > 500
    assert set(poses) == published_poses and len(poses) == len(published_poses)
    assert set(chunks) == published_chunks and len(chunks) == len(published_chunks)


def test_live_websocket_streams_a_published_pose(mosquitto_stack):
    """A pose published over MQTT arrives on /api/v1/live once it is stored."""
    import json

    from websockets.sync.client import connect

    stack = mosquitto_stack
    url = stack.api_url.replace("http://", "ws://") + "/api/v1/live"
    with connect(url, open_timeout=10) as ws:
        time.sleep(0.3)
        ts = now_ms()
        publish_all(
            stack,
            [
                (
                    "iot/coordinates/live-1",
                    encode_coordinates("live-1", format_timestamp(ts), 3.0, 4.0),
                )
            ],
        )
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            message = json.loads(ws.recv(timeout=30))
            if message.get("robotId") == "live-1":
                break
        assert message["robotId"] == "live-1" and message["position"][:2] == [3.0, 4.0]
        assert message["ts_ms"] == ts


def pose_rounds(stack):
    """`make_parts(round)` for merge_threads_lowered: ten poses of new robots a round."""
    start = now_ms() - 60_000

    def make_parts(round_: int) -> None:
        poses, _ = pose_and_chunk_messages(f"merge{round_}", robots=5, per_robot=2, start_ms=start)
        publish_all(stack, poses)

    return make_parts


def test_embedded_merges_run_at_a_lower_cpu_priority(mosquitto_stack):
    """`serve` holds the chDB directory: it sets ClickHouse's merge threads in it to
    MAPSERVICE_CHDB_MERGE_NICE (19 by default) once merges run, and no other thread."""
    merge_threads_lowered(mosquitto_stack.procs["server"].pid, pose_rounds(mosquitto_stack))
