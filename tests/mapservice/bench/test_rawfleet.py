"""The raw load fleet: the 2019 payloads byte for byte, its schedule, and what it counts as
published (only what the broker acknowledged), through Mosquitto and a broker that
acknowledges half."""

from __future__ import annotations

import base64
import socket
import threading
import time
import zlib

import msgspec
import paho.mqtt.client as mqtt

from mapservice.adapters.mqtt_client import PollingClient
from mapservice.adapters.ros_map import load_ros_map
from mapservice.bench.fleet.mqtt_packets import varint
from mapservice.bench.fleet.rawfleet import RawFleet
from mapservice.bench.fleet.rawfleet_plan import (
    WorkerPlan,
    chunk_payload,
    pose_templates,
    scheduled_messages,
)
from mapservice.core.wire2019 import (
    Limits,
    decode_chunk_create,
    decode_coordinates,
    encode_chunk_create,
    parse_timestamp,
)
from mapservice.robot import DEFAULT_MAP
from mapservice.robot.schedule import chunk_follows, chunk_phase, chunks_after


def _payload(template, timestamp: bytes) -> bytes:
    return template.prefix + timestamp + template.suffix


def test_pose_templates_are_the_2019_coordinates_message_with_the_timestamp_filled_in() -> None:
    """Each pre-encoded pose, once its timestamp is in, is what encode_coordinates makes,
    and the gateway's decoder takes it."""
    templates = pose_templates("robot-0042", 42, (10.0, 5.0), "iot/coordinates/robot-0042")
    ts = b"2026-11-23T15:00:00.250"
    payload = _payload(templates[3], ts)
    doc = msgspec.json.decode(payload)
    assert doc["robotId"] == "robot-0042" and doc["timestamp"] == ts.decode()
    assert set(doc) == {"robotId", "timestamp", "pose", "status"}
    assert len({_payload(t, ts) for t in templates}) == len(templates)  # a robot moves
    event = decode_coordinates("robot-0042", payload, parse_timestamp(ts.decode()), Limits())
    assert event.robot_id == "robot-0042" and event.event_time_ms == parse_timestamp(ts.decode())


def test_chunk_payload_is_byte_for_byte_encode_chunk_create() -> None:
    """The chunk message built from pre-computed base64 equals the 2019 encoder's."""
    pixels = bytes(range(256)) * 39 + bytes(16)
    b64 = base64.b64encode(zlib.compress(pixels))
    for row, col, robot in ((0, 0, "robot-0000"), (16, 10, "r:1@x.y-z_")):
        ts = "2026-11-23T15:00:01"
        assert chunk_payload(b64, row, col, ts.encode(), robot.encode()) == encode_chunk_create(
            row, col, pixels, ts, robot
        )


def test_schedule_counts_each_robots_poses_from_its_offset_and_every_fifth_chunk() -> None:
    """Robot i of n is due at i/n of a second, then every second: in 10 s robot 0 has
    10 poses (2 chunks), robot 5 of 10 also 10 (its last at 9.5 s)."""
    plan = WorkerPlan(
        host="h",
        port=1,
        robot_ids=["a", "b"],
        indices=[0, 5],
        fleet_size=10,
        centres=[(0, 0)] * 2,
        chunk_topics=["t"] * 2,
        chunk_b64=[b""],
        chunk_rows=1,
        chunk_cols=1,
        seconds=10,
    )
    assert scheduled_messages(plan, 10) == (20, 4)
    assert scheduled_messages(plan, 9.4) == (19, 3)


def test_the_fleets_chunks_spread_over_the_chunk_period_unless_aligned() -> None:
    """Robots 0-9 over 5 s send chunks after poses 5, 4, 3, 2, 1, 5, ... (two per second);
    aligned, all ten after their fifth pose."""
    plan = WorkerPlan(
        host="h",
        port=1,
        robot_ids=[f"r{i}" for i in range(10)],
        indices=list(range(10)),
        fleet_size=10,
        centres=[(0, 0)] * 10,
        chunk_topics=["t"] * 10,
        chunk_b64=[b""],
        chunk_rows=1,
        chunk_cols=1,
        seconds=10,
    )
    per_second = [scheduled_messages(plan, s)[1] for s in (1, 2, 3, 4, 5)]
    assert per_second == [2, 4, 6, 8, 10]
    aligned = WorkerPlan(**{**plan.__dict__, "aligned_chunks": True})
    assert [scheduled_messages(aligned, s)[1] for s in (1, 2, 3, 4, 5)] == [0, 0, 0, 0, 10]
    phases = [chunk_phase(i, 5) for i in range(10)]
    firsts = [next(k for k in range(1, 6) if chunk_follows(k, p, 5)) for p in phases]
    assert firsts == [5, 4, 3, 2, 1, 5, 4, 3, 2, 1]
    assert all(
        chunks_after(n, p, 5) == sum(chunk_follows(k, p, 5) for k in range(1, n + 1))
        for p in range(5)
        for n in range(12)
    )


def test_every_message_through_mosquitto_is_published_once_and_valid(mosquitto) -> None:
    """20 robots for 3 s from two workers: a paho subscriber receives exactly the messages
    the fleet counts as published, each a valid 2019 message, and the schedule is kept."""
    received: list[tuple[str, bytes]] = []
    sub = PollingClient(mqtt.CallbackAPIVersion.VERSION2, client_id="rawfleet-test-sub")
    subscribed = threading.Event()
    sub.on_message = lambda _c, _u, m: received.append((m.topic, m.payload))
    sub.on_subscribe = lambda *_a: subscribed.set()
    sub.connect("127.0.0.1", mosquitto)
    sub.subscribe([("iot/#", 1)])
    sub.loop_start()
    try:
        assert subscribed.wait(10)
        fleet = RawFleet(
            f"mqtt://127.0.0.1:{mosquitto}", load_ros_map(DEFAULT_MAP), 20, processes=2
        )
        stats = fleet.run(3)
        deadline = time.monotonic() + 10
        while len(received) < len(stats.published) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        sub.loop_stop()
        sub.disconnect()
    report = stats.report
    assert report["errors"] == [] and report["unacknowledged_events"] == 0
    # 60 poses; chunks spread (schedule.py): in 3 s, those of the 12 robots whose cycle is 2-4 poses ahead
    assert report["acknowledged_events"] == report["scheduled_events"] == len(stats.published) == 72
    assert report["workers"] == 2 and report["cpu_s"] > 0
    limits = Limits(chunk_rows=100, chunk_cols=100)
    got = set()
    for topic, payload in received:
        if topic == "iot/chunks/create":
            event = decode_chunk_create(payload, int(time.time() * 1000), limits)
            got.add(("chunk", event.robot_id, event.event_time_ms))
        else:
            event = decode_coordinates(
                topic.rsplit("/", 1)[1], payload, int(time.time() * 1000), limits
            )
            got.add(("pose", event.robot_id, event.event_time_ms))
    assert len(received) == len(got) == len(stats.published)
    assert got == {(kind, robot, ts) for kind, robot, ts, _ in stats.published}
    assert stats.poses == 60 and stats.chunks == 12


class HalfAckBroker(threading.Thread):
    """Accepts one connection, CONNACKs it and acknowledges every second PUBLISH."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.publishes = 0

    def run(self) -> None:
        conn, _ = self.server.accept()
        buf = b""
        with conn:
            while True:
                data = conn.recv(65536)
                if not data:
                    return
                buf += data
                while len(buf) >= 2:
                    length, shift, i = 0, 0, 1
                    while i < len(buf):
                        length |= (buf[i] & 0x7F) << shift
                        shift += 7
                        i += 1
                        if not buf[i - 1] & 0x80:
                            break
                    else:
                        break
                    if len(buf) < i + length:
                        break
                    kind, body, buf = buf[0] >> 4, buf[i : i + length], buf[i + length :]
                    if kind == 1:
                        conn.sendall(b"\x20\x02\x00\x00")
                    elif kind == 3:
                        topic_len = int.from_bytes(body[:2], "big")
                        pid = body[2 + topic_len : 4 + topic_len]
                        self.publishes += 1
                        if self.publishes % 2 == 0:
                            conn.sendall(b"\x40" + varint(2) + pid)


def test_only_acknowledged_messages_count_as_published() -> None:
    """Against a broker that acknowledges every second message, the fleet reports half of
    what it wrote as published and the rest as unacknowledged."""
    broker = HalfAckBroker()
    broker.start()
    fleet = RawFleet(
        f"mqtt://127.0.0.1:{broker.port}",
        load_ros_map(DEFAULT_MAP),
        10,
        processes=1,
        connections=1,
        ack_wait_s=0.5,
    )
    stats = fleet.run(2)
    report = stats.report
    # 20 poses and the chunks of robots 3, 4, 8 and 9 (their cycles are 3-4 poses ahead)
    assert report["written_events"] == broker.publishes == 24
    assert report["acknowledged_events"] == len(stats.published) == 12
    assert report["unacknowledged_events"] == 12 and report["schedule_percent"] == 50.0


def test_the_paho_fleet_schedules_as_many_chunks_as_the_raw_one() -> None:
    """RobotFleet's estimate for 10 robots over 5 s: 50 poses and 10 chunks, spread or aligned;
    over 3 s, 6 chunks spread (robots 2-4 and 7-9) and none aligned."""
    from mapservice.robot.loadgen import RobotFleet

    ros_map = load_ros_map(DEFAULT_MAP)
    spread = RobotFleet("mqtt://127.0.0.1:9", ros_map, 10)
    aligned = RobotFleet("mqtt://127.0.0.1:9", ros_map, 10, aligned_chunks=True)
    assert spread.scheduled_events(5) == aligned.scheduled_events(5) == 60
    assert (spread.scheduled_events(3), aligned.scheduled_events(3)) == (36, 30)
