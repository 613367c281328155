"""A load fleet that is not the limit: pre-encoded MQTT packets on raw sockets, QoS 1.

`RobotFleet` (loadgen.py) publishes through paho: ~300 µs of CPU per message, so at
4,000 robots it took more than half a core and fell behind its schedule. `RawFleet` sends
the same 2019 workload (one pose a second per robot, one chunk every five seconds, the
same payloads `encode_coordinates` / `encode_chunk_create` make) from worker processes,
each an asyncio loop writing pre-encoded PUBLISH packets (`mqtt_packets.PublishTemplate`:
only the timestamp and the packet id are filled in per message) on a few connections.

Honest accounting: a message counts as published when the broker's PUBACK for it
arrived; the workers stream (robot, kind, event time, write time) of every acknowledged
message back, and report what their schedule asked for, what they wrote, how late, and
their own CPU time. Poses drive circles as `RobotFleet`'s do, in `POSE_PHASES` steps per
lap, each step pre-encoded per robot.
"""

from __future__ import annotations

import base64
import random
import socket
import subprocess
import sys
import threading
import time
import zlib
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait

from mapservice.bench.fleet.rawfleet_plan import (
    ACK_WAIT_S,
    KINDS,
    POSE,
    WorkerPlan,
    default_processes,
    percentile,
)


@dataclass
class FleetStats:
    """What `RawFleet.run` returns; `published` as `LoadStats.published`: (kind, robot id,
    event time ms, publish wall time) of every acknowledged message, in arrival order."""

    poses: int = 0
    chunks: int = 0
    published: list[tuple[str, str, int, float]] = field(default_factory=list)
    report: dict = field(default_factory=dict)


class RawFleet:
    """The 2019 workload for `robots` robots from `processes` worker processes.

    `start()` spawns the workers and connects them (they pre-encode their robots' packets
    first); `run(seconds)` starts every worker on one clock and collects what the broker
    acknowledged until they are done. `pids` are the workers' process ids (for CPU
    accounting from outside); `stats.report` holds the schedule and CPU figures."""

    def __init__(
        self,
        mqtt_url: str,
        ros_map,
        robots: int,
        *,
        prefix: str = "robot",
        processes: int | None = None,
        connections: int = 2,
        pose_period_s: float = 1.0,
        chunk_period_s: float = 5.0,
        seed: int = 7,
        mqtt_conn=None,
        nice: int = 0,
        ack_wait_s: float = ACK_WAIT_S,
        aligned_chunks: bool = False,
    ) -> None:
        import numpy as np

        from mapservice.adapters.mqtt_client import parse_mqtt_url
        from mapservice.adapters.ros_map import free_cells_metres, meta_for, slice_chunks
        from mapservice.robot.connection import RobotMqtt
        from mapservice.robot.loadgen import fleet_robot_id

        self.conn = mqtt_conn or RobotMqtt(mqtt_url)
        host, port, tls = parse_mqtt_url(self.conn.url)
        if tls:
            raise ValueError("RawFleet speaks plain MQTT; use RobotFleet (paho) for mqtts://")
        self.robots = [fleet_robot_id(prefix, i) for i in range(robots)]
        self.conn.check(self.robots)
        meta = meta_for(ros_map)
        chunks = list(slice_chunks(ros_map).values())
        b64 = [base64.b64encode(zlib.compress(p)) for p in chunks]
        free = free_cells_metres(ros_map)
        picks = free[np.random.default_rng(seed).integers(0, len(free), size=max(robots, 1))]
        centres = [(float(x), float(y)) for x, y in picks]
        self.processes = max(1, min(processes or default_processes(robots), max(robots, 1)))
        self.plans: list[WorkerPlan] = []
        for w in range(self.processes):
            idx = list(range(w, robots, self.processes))  # interleaved: each spans the second
            ids = [self.robots[i] for i in idx]
            creds = [(r, self.conn.password(r)) for r in ids] if self.conn.authenticated else None
            self.plans.append(
                WorkerPlan(
                    host=host,
                    port=port,
                    robot_ids=ids,
                    indices=idx,
                    fleet_size=robots,
                    centres=[centres[i] for i in idx],
                    chunk_topics=[self.conn.chunk_topic(r) for r in ids],
                    chunk_b64=b64,
                    chunk_rows=meta.chunk_rows,
                    chunk_cols=meta.chunk_cols,
                    seconds=None,
                    pose_period_s=pose_period_s,
                    chunk_period_s=chunk_period_s,
                    aligned_chunks=aligned_chunks,
                    seed=seed + w,
                    connections=connections,
                    credentials=creds,
                    nice=nice,
                    ack_wait_s=ack_wait_s,
                    client_prefix=f"rawfleet-{random.Random(seed).getrandbits(32):08x}",
                )
            )
        self.stats = FleetStats()
        self.pids: list[int] = []
        self._procs: list = []
        self._pipes: list[Connection] = []
        self._stop = threading.Event()
        self._ack_lags: list[float] = []  # write -> PUBACK per acknowledged message

    def start(self, seconds: float | None, timeout_s: float = 120.0) -> None:
        """Spawns and connects the workers; returns once each is ready to publish."""
        # A fresh interpreter per worker (not fork: the caller runs threads; not
        # multiprocessing's spawn: it re-runs the caller's main script).
        code = (
            "from mapservice.bench.fleet.rawfleet_worker import worker_main; import sys; "
            "worker_main(int(sys.argv[1]))"
        )
        for plan in self.plans:
            parent, child = socket.socketpair()
            proc = subprocess.Popen(
                [sys.executable, "-c", code, str(child.fileno())], pass_fds=[child.fileno()]
            )
            child.close()
            pipe = Connection(parent.detach())
            pipe.send(WorkerPlan(**{**plan.__dict__, "seconds": seconds}))
            self._procs.append(proc)
            self._pipes.append(pipe)
        deadline = time.monotonic() + timeout_s
        for pipe in self._pipes:
            if not pipe.poll(max(0.0, deadline - time.monotonic())):
                self.close()
                raise TimeoutError("a load fleet worker did not connect in time")
            try:
                message = pipe.recv()
            except EOFError:
                self.close()
                raise RuntimeError("a load fleet worker exited before it was ready") from None
            if message[0] != "ready":
                self.close()
                raise RuntimeError(f"a load fleet worker failed: {message[1:]}")
            self.pids.append(message[1])

    def stop(self) -> None:
        self._stop.set()

    def run(
        self, seconds: float | None = None, on_tick: Callable[[FleetStats], None] | None = None
    ) -> FleetStats:
        """Publishes for `seconds` (until `stop()` if None); returns when every worker
        reported its last acknowledged message."""
        if not self._procs:
            self.start(seconds)
        t0 = time.monotonic() + 0.05
        for pipe in self._pipes:
            pipe.send(("go", t0))
        reports: list[dict] = []
        live = list(self._pipes)
        stop_sent = False
        try:
            while live:
                if self._stop.is_set() and not stop_sent:
                    for pipe in live:
                        pipe.send(("stop",))
                    stop_sent = True
                for pipe in wait(live, timeout=0.25):
                    try:
                        message = pipe.recv()
                    except EOFError:
                        live.remove(pipe)
                        reports.append({"errors": ["worker exited without its report"]})
                        continue
                    if message[0] == "acked":
                        self._take(*message[1:])
                    elif message[0] == "done":
                        reports.append(message[1])
                        live.remove(pipe)
                    elif message[0] == "failed":
                        raise RuntimeError(f"a load fleet worker failed: {message[1]}")
                if on_tick is not None:
                    on_tick(self.stats)
        finally:
            self.close()
        self.stats.report = {
            **summarize(reports),
            "puback_p50_s": percentile(self._ack_lags, 50),
            "puback_p99_s": percentile(self._ack_lags, 99),
        }
        return self.stats

    def _take(self, idx_kind: array, tss: array, walls: array, ack_walls: array) -> None:
        robots, out = self.robots, self.stats.published
        lags = self._ack_lags
        for ik, ts, wall, acked in zip(idx_kind, tss, walls, ack_walls):
            kind = ik & 1
            out.append((KINDS[kind], robots[ik >> 1], ts, wall))
            lags.append(acked - wall)
            if kind == POSE:
                self.stats.poses += 1
            else:
                self.stats.chunks += 1

    def close(self) -> None:
        for proc in self._procs:
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.terminate()
                proc.wait(5)
        for pipe in self._pipes:
            pipe.close()
        self._procs, self._pipes = [], []


def summarize(reports: list[dict]) -> dict:
    """The fleet's figures from its workers' reports."""
    total = lambda k: sum(r.get(k) or 0 for r in reports)  # noqa: E731
    scheduled = total("scheduled_poses") + total("scheduled_chunks")
    written = total("written_poses") + total("written_chunks")
    acknowledged = written - total("unacknowledged")
    wall = max((r.get("wall_s") or 0 for r in reports), default=0.0)
    lags = [r["lag_p99_s"] for r in reports if r.get("lag_p99_s") is not None]
    return {
        "workers": len(reports),
        "connections": total("connections"),
        "scheduled_events": scheduled,
        "written_events": written,
        "acknowledged_events": acknowledged,
        "unacknowledged_events": total("unacknowledged"),
        "schedule_percent": 100.0 * acknowledged / scheduled if scheduled else None,
        "lag_p99_s": max(lags) if lags else None,
        "lag_max_s": max((r.get("lag_max_s") or 0 for r in reports), default=None),
        "cpu_s": total("cpu_s"),
        "cpu_percent_of_one_core": 100.0 * total("cpu_s") / wall if wall else None,
        "cpu_us_per_event": 1e6 * total("cpu_s") / written if written else None,
        "errors": [e for r in reports for e in r.get("errors", [])][:10],
        "per_worker": reports,
    }
