"""Simulated robots speaking the 2019 MQTT contract.

Each robot publishes one pose a second and, like the 2019 load test (simple_simulator.py),
one chunk every five seconds: real chunks of a real map, re-sent at new positions.
Robots drive circles through free space of the map, as the 2019 automatic simulator did.
"""

from __future__ import annotations

import heapq
import math
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mapservice.adapters.ros_map import RosMap, free_cells_metres, meta_for, slice_chunks
from mapservice.core.wire2019 import encode_chunk_create, encode_coordinates, format_timestamp

from .connection import RobotClients, RobotMqtt
from .schedule import chunk_follows, chunk_phase, chunks_after


def fleet_robot_id(prefix: str, i: int) -> str:
    """The id of the load fleet's robot number `i` (`up --auth` gives each its credential)."""
    return f"{prefix}-{i:04d}"


@dataclass
class LoadStats:
    poses: int = 0
    chunks: int = 0
    published: list[tuple[str, str, int, float]] = field(default_factory=list)
    # (kind, robot id, event time ms, publish wall time) when recording is on


class RobotFleet:
    """Publishes the 2019 workload for `robots` robots through one MQTT connection."""

    def __init__(
        self,
        mqtt_url: str,
        ros_map: RosMap,
        robots: int,
        *,
        prefix: str = "robot",
        pose_period_s: float = 1.0,
        chunk_period_s: float = 5.0,
        seed: int = 7,
        record: bool = False,
        qos: int = 1,
        mqtt_conn: RobotMqtt | None = None,
        aligned_chunks: bool = False,
    ) -> None:
        self.mqtt_url = mqtt_url
        # Where robots have credentials, each connects as itself (one connection per robot).
        self.conn = mqtt_conn or RobotMqtt(mqtt_url)
        self.meta = meta_for(ros_map)
        self.chunks = list(slice_chunks(ros_map).values())
        self.robots = [fleet_robot_id(prefix, i) for i in range(robots)]
        self.conn.check(self.robots)
        self.pose_period_s = pose_period_s
        self.chunk_period_s = chunk_period_s
        self.aligned_chunks = (
            aligned_chunks  # every robot's chunk after the same pose (schedule.py)
        )
        self.record = record
        self.qos = qos
        self.stats = LoadStats()
        self._rng = random.Random(seed)
        free = free_cells_metres(ros_map)
        picks = free[np.random.default_rng(seed).integers(0, len(free), size=max(robots, 1))]
        self._centres = [(float(x), float(y)) for x, y in picks]
        self._stop = threading.Event()
        self._lock = threading.Lock()

    def stop(self) -> None:
        self._stop.set()

    def scheduled_events(self, seconds: float) -> int:
        """Poses and chunks the schedule asks for in `seconds`, counting whole pose periods
        per robot (an estimate: the run's last period may be cut short)."""
        per_chunk = round(self.chunk_period_s / self.pose_period_s)
        poses = int(seconds / self.pose_period_s)
        return sum(
            poses + chunks_after(poses, chunk_phase(i, per_chunk, self.aligned_chunks), per_chunk)
            for i in range(len(self.robots))
        )

    def _pose(self, i: int, robot: str, now_ms: int) -> bytes:
        cx, cy = self._centres[i]
        angle = (now_ms / 1000.0) * 0.2 + i
        x, y = cx + 1.0 * math.cos(angle), cy + 1.0 * math.sin(angle)
        yaw = angle + math.pi / 2
        battery = 100.0 - ((now_ms / 1000.0 / 60.0 + i) % 100.0)
        return encode_coordinates(
            robot,
            format_timestamp(now_ms),
            round(x, 3),
            round(y, 3),
            (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
            battery_level=round(battery, 1),
            charging=battery < 20,
            loaded=(i + now_ms // 60000) % 2 == 0,
        )

    def run(
        self, seconds: float | None, on_tick: Callable[[LoadStats], None] | None = None
    ) -> LoadStats:
        clients = RobotClients(self.conn, self.robots, f"loadgen-{self._rng.getrandbits(32):08x}")
        clients.connect()
        n = len(self.robots)
        started = time.monotonic()
        # Robots are spread evenly over each second so the load is smooth. A heap of
        # (due time, robot index) finds the next robot in O(log n) per message.
        due_heap = [(started + (i / max(n, 1)) * self.pose_period_s, i) for i in range(n)]
        heapq.heapify(due_heap)
        pose_count = [0] * n
        per_chunk = round(self.chunk_period_s / self.pose_period_s)
        phases = [chunk_phase(i, per_chunk, self.aligned_chunks) for i in range(n)]
        last_ts = [0] * n
        pending: list = []
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if seconds is not None and now - started >= seconds:
                    break
                due, i = due_heap[0]
                wait = due - now
                if wait > 0:
                    self._stop.wait(min(wait, 0.5))
                    continue
                robot = self.robots[i]
                now_ms = max(time.time_ns() // 1_000_000, last_ts[i] + 1)
                last_ts[i] = now_ms
                pending.append(
                    clients.publish(
                        robot,
                        f"iot/coordinates/{robot}",
                        self._pose(i, robot, now_ms),
                        qos=self.qos,
                    )
                )
                self.stats.poses += 1
                if self.record:
                    self.stats.published.append(("pose", robot, now_ms, time.time()))
                pose_count[i] += 1
                if chunk_follows(pose_count[i], phases[i], per_chunk):
                    row = self._rng.randrange(self.meta.chunk_rows)
                    col = self._rng.randrange(self.meta.chunk_cols)
                    pixels = self._rng.choice(self.chunks)
                    pending.append(
                        clients.publish(
                            robot,
                            self.conn.chunk_topic(robot),
                            encode_chunk_create(row, col, pixels, format_timestamp(now_ms), robot),
                            qos=self.qos,
                        )
                    )
                    self.stats.chunks += 1
                    if self.record:
                        self.stats.published.append(("chunk", robot, now_ms, time.time()))
                heapq.heapreplace(due_heap, (due + self.pose_period_s, i))
                if self.stats.poses % max(n, 1) == 0:
                    pending = [p for p in pending if not p.is_published()]
                    if on_tick is not None:
                        on_tick(self.stats)
        finally:
            # QoS 1: the run ends when the broker has acknowledged every message.
            deadline = time.monotonic() + 30
            for info in pending:
                info.wait_for_publish(max(0.0, deadline - time.monotonic()))
            clients.close()
        return self.stats
