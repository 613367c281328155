"""The robot agent without brokers: the 2019 start-up sequence against an in-memory 2019
chunk service (httpx.MockTransport), change detection by content hash with a threshold,
integration of advertised chunks, odometry parsing."""

from __future__ import annotations

import base64
import json
import shutil
import zlib
from dataclasses import dataclass, field

import httpx
import msgspec
import numpy as np
import pytest

from mapservice.adapters.ros_map import load_ros_map
from mapservice.robot.agent import RobotAgent
from mapservice.robot.local_map import LocalMap, decode_chunk_doc
from mapservice.robot.pose_sources import parse_odometry
from tests.fixtures.paths import MAPS


@dataclass
class FakeChunkService:
    """Appendix A.1 in memory: meta, POST/GET chunks (latest), chunk by id."""

    meta: dict | None = None
    chunks: list[dict] = field(default_factory=list)
    requests: list[tuple[str, str]] = field(default_factory=list)

    def handler(self, request: httpx.Request) -> httpx.Response:
        path, method = request.url.path, request.method
        self.requests.append((method, path))
        if path == "/api/chunk-service/meta":
            if method == "POST":
                self.meta = json.loads(request.content)
                return httpx.Response(200, json={"result": "created"})
            return (
                httpx.Response(200, json=self.meta) if self.meta else httpx.Response(404, json={})
            )
        if path == "/api/chunk-service/chunks" and method == "POST":
            body = json.loads(request.content)
            doc = {
                "row": body["row"],
                "column": body["column"],
                "timestamp": body["timestamp"],
                "chunk": body["pgmB64compressedData"],
                "type": "pgm_base64_compressed",
                "id": f"row:{body['row']}_column:{body['column']}_{body['timestamp']}",
                "robotId": body["robotId"],
            }
            self.chunks.append(doc)
            return httpx.Response(200, json={"_id": doc["id"], "result": "created"})
        if path == "/api/chunk-service/chunks":
            assert request.url.params["latest"] == "true"
            latest: dict = {}
            for doc in self.chunks:
                latest[(doc["row"], doc["column"])] = doc
            skip, limit = int(request.url.params["skip"]), int(request.url.params["limit"])
            return httpx.Response(200, json=list(latest.values())[skip : skip + limit])
        if path.startswith("/api/chunk-service/chunks/id/"):
            wanted = path.rsplit("/", 1)[1]
            doc = next((d for d in self.chunks if d["id"] == wanted), None)
            return httpx.Response(200, json=doc) if doc else httpx.Response(404)
        return httpx.Response(404)

    def advertise(self, doc: dict) -> bytes:
        return msgspec.json.encode(
            {
                "row": doc["row"],
                "column": doc["column"],
                "timestamp": doc["timestamp"],
                "robotId": doc["robotId"],
                "chunkUrl": f"http://svc/api/chunk-service/chunks/id/{doc['id']}",
            }
        )


class CapturingClient:
    def __init__(self) -> None:
        self.published: list[tuple[str, bytes]] = []

    def publish(self, topic, payload, qos=0):
        self.published.append((topic, payload))


def robot_copy(tmp_path, name: str):
    (tmp_path / name).mkdir()
    for suffix in ("yaml", "pgm"):
        shutil.copy(MAPS / f"depot.{suffix}", tmp_path / name / f"depot.{suffix}")
    return tmp_path / name / "depot.yaml"


def make_agent(tmp_path, name, service, **kw) -> RobotAgent:
    http = httpx.Client(base_url="http://svc", transport=httpx.MockTransport(service.handler))
    agent = RobotAgent(
        robot_copy(tmp_path, name), name, "http://svc", "mqtt://unused", http=http, **kw
    )
    agent.client = CapturingClient()
    return agent


def edit_map(yaml_path, row0, col0, size, value) -> None:
    from mapservice.adapters.ros_map import write_pgm

    m = load_ros_map(yaml_path)
    pixels = m.pixels.copy()
    pixels[row0 : row0 + size, col0 : col0 + size] = value
    write_pgm(yaml_path.with_suffix(".pgm"), pixels, comment=m.comment)


def test_first_robot_uploads_meta_and_chunks_second_downloads(tmp_path) -> None:
    """With no meta stored the robot POSTs meta then all 28 chunks; the next robot finds the
    meta and downloads the map (GET chunks?latest=true) into its map file."""
    service = FakeChunkService()
    a = make_agent(tmp_path, "robot-a", service)
    assert a.start() == "uploaded"
    assert service.requests[:2] == [
        ("GET", "/api/chunk-service/meta"),
        ("POST", "/api/chunk-service/meta"),
    ]
    assert service.meta["CHUNK_ROWS"] == 4 and service.meta["resolution"] == 0.05
    assert len(service.chunks) == 4 * 7 and {c["robotId"] for c in service.chunks} == {"robot-a"}
    # Robot B starts with a different local map: the service's wins.
    b = make_agent(tmp_path, "robot-b", service)
    edit_map(b.map_yaml, 10, 10, 30, 0)
    assert b.start() == "downloaded"
    assert np.array_equal(load_ros_map(b.map_yaml).pixels, load_ros_map(MAPS / "depot.yaml").pixels)


def test_changes_propagate_from_one_robot_to_another(tmp_path) -> None:
    """Robot A edits its map file; it publishes just the touched chunk; once the service has
    it and advertises it, robot B's map file holds the same pixels as A's."""
    service = FakeChunkService()
    a, b = make_agent(tmp_path, "robot-a", service), make_agent(tmp_path, "robot-b", service)
    a.start()
    b.start()
    edit_map(a.map_yaml, 150, 250, 40, 0)  # a pallet in chunk (1, 2)
    assert a.publish_local_changes() == 1
    topic, payload = a.client.published[-1]
    body = msgspec.json.decode(payload)
    assert topic == "iot/chunks/create" and (body["row"], body["column"]) == (1, 2)
    # The service stores it (as ingest would) and advertises it (as processors would).
    service.handler(httpx.Request("POST", "http://svc/api/chunk-service/chunks", json=body))
    b.adverts.put(service.advertise(service.chunks[-1]))
    a.adverts.put(service.advertise(service.chunks[-1]))  # its own: ignored
    assert b.integrate_adverts() == 1 and a.integrate_adverts() == 0
    assert np.array_equal(load_ros_map(b.map_yaml).pixels, load_ros_map(a.map_yaml).pixels)
    # B wrote the file itself: that is not a local change to publish back.
    assert b.publish_local_changes() == 0 and b.client.published == []


def test_threshold_ignores_small_changes_until_they_add_up() -> None:
    """With threshold 0.05 a 3x3 px change of a 100x100 chunk is not published; a 30x30 one
    is; an unchanged map publishes nothing."""
    m = load_ros_map(MAPS / "depot.yaml")
    local = LocalMap.of(m)
    assert local.changes(m.pixels.copy(), 0.05) == []
    pixels = m.pixels.copy()
    pixels[5:8, 5:8] = 0 if pixels[5, 5] else 254
    assert local.changes(pixels, 0.05) == []
    pixels = pixels.copy()
    pixels[120:150, 120:150] = 17
    changed = local.changes(pixels, 0.05)
    assert [(r, c) for r, c, _ in changed] == [(1, 1)]
    assert local.changes(pixels, 0.05) == []  # now known: hashes equal


def test_decode_chunk_doc_and_odometry() -> None:
    """Chunk documents decode to pixels; odometry is read as nav_msgs/Odometry, a bare Pose
    or garbage (None)."""
    raw = bytes(range(100)) * 100
    doc = {
        "row": 1,
        "column": 2,
        "chunk": base64.b64encode(zlib.compress(raw)).decode(),
        "type": "pgm_base64_compressed",
    }
    assert decode_chunk_doc(doc) == (1, 2, raw)
    with pytest.raises(ValueError):
        decode_chunk_doc({**doc, "type": "png"})
    odom = {
        "header": {"frame_id": "odom"},
        "pose": {
            "pose": {
                "position": {"x": 1.5, "y": -2, "z": 0},
                "orientation": {"x": 0, "y": 0, "z": 0.7071, "w": 0.7071},
            },
            "covariance": [],
        },
    }
    reading = parse_odometry(msgspec.json.encode(odom))
    assert (reading.x, reading.y, reading.yaw_q[2]) == (1.5, -2.0, 0.7071)
    bare = parse_odometry(b'{"position": {"x": 3, "y": 4}, "battery": 55, "loaded": true}')
    assert (bare.x, bare.y, bare.battery, bare.loaded, bare.yaw_q) == (
        3.0,
        4.0,
        55.0,
        True,
        (0, 0, 0, 1),
    )
    assert parse_odometry(b"not json") is None and parse_odometry(b'{"pose": 3}') is None


def test_simulated_pose_source_publishes_a_2019_pose(tmp_path) -> None:
    """With the simulated pose source, each tick publishes one listing-16 pose (with a
    planned path once the robot has a route) on iot/coordinates/<robotId>."""
    from mapservice.robot.pose_sources import SimulatedPose

    service = FakeChunkService()
    agent = make_agent(tmp_path, "robot-s", service)
    agent.pose_source = SimulatedPose(agent.ros_map, "robot-s")
    agent.start()
    for _ in range(3):
        agent.tick()
    poses = [
        msgspec.json.decode(p) for t, p in agent.client.published if t == "iot/coordinates/robot-s"
    ]
    assert len(poses) == 3 and poses[0]["robotId"] == "robot-s"
    assert {"pose", "status", "timestamp"} <= set(poses[0])


def test_integrating_keeps_unpublished_local_edits(tmp_path) -> None:
    """An advertisement arriving while the map file holds an unpublished edit elsewhere:
    the advertised chunk is written, the local edit survives and is published next."""
    service = FakeChunkService()
    a, b = make_agent(tmp_path, "robot-a", service), make_agent(tmp_path, "robot-b", service)
    a.start()
    b.start()
    edit_map(a.map_yaml, 150, 250, 40, 0)  # A: chunk (1, 2)
    a.publish_local_changes()
    body = msgspec.json.decode(a.client.published[-1][1])
    service.handler(httpx.Request("POST", "http://svc/api/chunk-service/chunks", json=body))
    edit_map(b.map_yaml, 20, 520, 30, 0)  # B: chunk (0, 5), not yet published
    b.adverts.put(service.advertise(service.chunks[-1]))
    b.tick()  # integrates A's chunk; 2019: no local check in the same iteration
    on_disk = load_ros_map(b.map_yaml).pixels
    assert (on_disk[150:190, 250:290] == 0).all() and (on_disk[20:50, 520:550] == 0).all()
    assert b.client.published == []
    b.tick()
    chunks = [msgspec.json.decode(p) for t, p in b.client.published if t == "iot/chunks/create"]
    assert [(c["row"], c["column"]) for c in chunks] == [(0, 5)]


def test_a_robot_with_a_map_of_another_size_refuses_and_stores_nothing(tmp_path) -> None:
    """The service stores the warehouse (1006 x 1674): a depot robot's start raises a message
    naming both sizes, posts nothing, and leaves its own map file as it was."""
    from mapservice.adapters.ros_map import meta_for
    from mapservice.robot.chunks import meta_to_json

    service = FakeChunkService(meta=meta_to_json(meta_for(load_ros_map(MAPS / "warehouse.yaml"))))
    a = make_agent(tmp_path, "robot-a", service)
    before = a.image_path.read_bytes()
    with pytest.raises(RuntimeError, match=r"1006 x 1674.*604 x 307"):
        a.start()
    assert [m for m, _ in service.requests] == ["GET"] and service.chunks == []
    assert a.image_path.read_bytes() == before


def test_agent_with_a_credential_publishes_chunks_on_its_own_topic(tmp_path) -> None:
    """An agent given its own MQTT credential sends changed chunks to iot/chunks/create/<robotId>
    (the only chunk topic the broker lets it use); one without a credential for its id refuses
    to start."""
    from mapservice.robot.connection import RobotMqtt

    service = FakeChunkService()
    a = make_agent(
        tmp_path, "robot-a", service, mqtt_conn=RobotMqtt("mqtt://unused", {"robot-a": "pw"})
    )
    a.start()
    edit_map(a.map_yaml, 150, 250, 40, 0)
    assert a.publish_local_changes() == 1
    assert a.client.published[-1][0] == "iot/chunks/create/robot-a"
    with pytest.raises(ValueError, match="no credential"):
        make_agent(
            tmp_path, "robot-b", service, mqtt_conn=RobotMqtt("mqtt://unused", {"robot-a": "pw"})
        )


def test_the_agent_obeys_commands_with_its_simulated_pose_and_refuses_with_odometry(
    tmp_path,
) -> None:
    """`mapservice robot` with the simulated pose: a pause on its own command topic holds its
    reported position from the next tick on, acked and done on its answer topic; with an
    odometry source it cannot drive the robot, so it rejects the command, saying why."""
    from types import SimpleNamespace

    from mapservice.core.commands import CommandIssued, command_message
    from mapservice.robot.commands import command_topic, response_topic
    from mapservice.robot.pose_sources import SimulatedPose

    def command(robot: str, cid: str) -> SimpleNamespace:
        issued = CommandIssued(cid, robot, "pause", "operator:x", 0)
        return SimpleNamespace(
            topic=command_topic(robot), payload=msgspec.json.encode(command_message(issued))
        )

    source = SimulatedPose(load_ros_map(MAPS / "depot.yaml"), "agv-9")
    agent = make_agent(tmp_path, "agv-9", FakeChunkService(), pose_source=source)
    agent._on_message(None, None, command("agv-9", "c-1"))
    assert agent.adverts.empty()  # a command is no advertisement
    agent.tick()
    held = [
        json.loads(p)["pose"]["position"]
        for t, p in agent.client.published
        if t == "iot/coordinates/agv-9"
    ][-1]
    answers = [json.loads(p) for t, p in agent.client.published if t == response_topic("agv-9")]
    assert [(a["type"], a.get("status") or a.get("outcome")) for a in answers] == [
        ("ack", "accepted"),
        ("outcome", "done"),
    ]
    for _ in range(5):
        agent.tick()
    positions = [
        json.loads(p)["pose"]["position"]
        for t, p in agent.client.published
        if t == "iot/coordinates/agv-9"
    ]
    assert positions[-5:] == [held] * 5

    odometry = make_agent(tmp_path, "agv-8", FakeChunkService())  # no simulated pose
    odometry._on_message(None, None, command("agv-8", "c-2"))
    assert odometry.answer_commands() == 1
    ((topic, payload),) = odometry.client.published
    assert topic == response_topic("agv-8")
    assert (
        json.loads(payload)["status"] == "rejected" and "odometry" in json.loads(payload)["reason"]
    )
