"""What a RawFleet worker publishes: its plan (robots, topics, chunks, schedule), the
pre-encoded pose templates and chunk payloads, and what its schedule asks for."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mapservice.bench.fleet.mqtt_packets import (
    PublishTemplate,
)
from mapservice.core.wire2019 import encode_coordinates
from mapservice.robot.schedule import chunk_phase, chunks_after

POSE, CHUNK = 0, 1
KINDS = ("pose", "chunk")
POSE_PHASES = 31  # pre-encoded poses per lap: 2π/31 rad a second, ~RobotFleet's 0.2 rad/s
TICK_S = 0.005  # a worker writes what fell due every 2-5 ms, one write per connection
MIN_TICK_S = 0.002
REPORT_EVERY_S = 0.25  # acknowledged messages go to the parent this often
KEEPALIVE_S = 60
ACK_WAIT_S = 30.0  # after the run, how long the workers wait for outstanding PUBACKs
MAX_IN_FLIGHT = 60_000  # per connection: packet ids are 16 bits
_TS_MARK = "@@TS@@"


def default_processes(robots: int) -> int:
    """Worker processes for a fleet: one per 4,000 robots (~5 µs of CPU a message each)."""
    return max(1, math.ceil(robots / 4000))


def chunk_payload(b64: bytes, row: int, column: int, timestamp: bytes, robot_id: bytes) -> bytes:
    """Exactly `encode_chunk_create`'s bytes, from the pixels' base64 computed once."""
    return b'{"pgmB64compressedData":"%s","row":%d,"column":%d,"timestamp":"%s","robotId":"%s"}' % (
        b64,
        row,
        column,
        timestamp,
        robot_id,
    )


def pose_templates(
    robot_id: str,
    index: int,
    centre: tuple[float, float],
    pose_topic: str,
    phases: int = POSE_PHASES,
) -> list[PublishTemplate]:
    """One pre-encoded PUBLISH per step of the robot's lap, its timestamp left open."""
    cx, cy = centre
    out = []
    for k in range(phases):
        angle = 2 * math.pi * k / phases + index
        yaw = angle + math.pi / 2
        battery = round(100.0 - ((index + k / phases) % 100.0), 1)
        payload = encode_coordinates(
            robot_id,
            _TS_MARK,
            round(cx + math.cos(angle), 3),
            round(cy + math.sin(angle), 3),
            (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
            battery_level=battery,
            charging=battery < 20,
            loaded=index % 2 == 0,
        )
        prefix, mark, suffix = payload.partition(_TS_MARK.encode())
        if not mark or _TS_MARK.encode() in suffix:
            raise ValueError(f"robot id {robot_id!r} holds the timestamp marker")
        out.append(PublishTemplate(pose_topic, prefix, suffix))
    return out


@dataclass(frozen=True)
class WorkerPlan:
    """What one worker process publishes: picklable, no map, no numpy."""

    host: str
    port: int
    robot_ids: list[str]
    indices: list[int]  # each robot's index in the whole fleet (its place in the second)
    fleet_size: int
    centres: list[tuple[float, float]]
    chunk_topics: list[str]
    chunk_b64: list[bytes]  # base64 of each zlib-compressed chunk picture
    chunk_rows: int
    chunk_cols: int
    seconds: float | None
    pose_period_s: float = 1.0
    chunk_period_s: float = 5.0
    aligned_chunks: bool = False  # every robot's chunk after the same pose (schedule.py)
    seed: int = 7
    connections: int = 2
    # Per robot (username, password) when robots have credentials: one connection each.
    credentials: list[tuple[str, str]] | None = None
    nice: int = 0
    client_prefix: str = "rawfleet"
    ack_wait_s: float = ACK_WAIT_S


def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return s[min(len(s) - 1, max(0, math.ceil(q / 100.0 * len(s)) - 1))]


def scheduled_messages(plan: WorkerPlan, seconds: float) -> tuple[int, int]:
    """(poses, chunks) a worker's schedule asks for in `seconds`: robot i's k-th pose is
    due at k periods plus its offset (i / fleet size of a period), every fifth is followed
    by a chunk (robot i's cycle offset by i poses: schedule.py)."""
    per_chunk = round(plan.chunk_period_s / plan.pose_period_s)
    poses = chunks = 0
    for i in plan.indices:
        offset = i / max(plan.fleet_size, 1) * plan.pose_period_s
        n = max(0, math.ceil((seconds - offset) / plan.pose_period_s))
        poses += n
        chunks += chunks_after(n, chunk_phase(i, per_chunk, plan.aligned_chunks), per_chunk)
    return poses, chunks
