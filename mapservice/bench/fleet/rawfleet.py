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

import asyncio
import base64
import math
import os
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

from mapservice.core.wire2019 import encode_coordinates, format_timestamp

from .mqtt_packets import (
    DISCONNECT_PACKET,
    PINGREQ_PACKET,
    PacketReader,
    ProtocolError,
    PublishTemplate,
    connect_packet,
)
from .schedule import chunk_follows, chunk_phase, chunks_after

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
        b64, row, column, timestamp, robot_id)


def pose_templates(robot_id: str, index: int, centre: tuple[float, float], pose_topic: str,
                   phases: int = POSE_PHASES) -> list[PublishTemplate]:
    """One pre-encoded PUBLISH per step of the robot's lap, its timestamp left open."""
    cx, cy = centre
    out = []
    for k in range(phases):
        angle = 2 * math.pi * k / phases + index
        yaw = angle + math.pi / 2
        battery = round(100.0 - ((index + k / phases) % 100.0), 1)
        payload = encode_coordinates(robot_id, _TS_MARK, round(cx + math.cos(angle), 3),
                                     round(cy + math.sin(angle), 3),
                                     (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
                                     battery_level=battery, charging=battery < 20,
                                     loaded=index % 2 == 0)
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


@dataclass
class FleetStats:
    """What `RawFleet.run` returns; `published` as `LoadStats.published`: (kind, robot id,
    event time ms, publish wall time) of every acknowledged message, in arrival order."""

    poses: int = 0
    chunks: int = 0
    published: list[tuple[str, str, int, float]] = field(default_factory=list)
    report: dict = field(default_factory=dict)


# --- the worker process -----------------------------------------------------------------


class _Connection(asyncio.Protocol):
    """One MQTT connection: writes batches, matches PUBACKs to what is in flight."""

    def __init__(self, acked: list, errors: list) -> None:
        self.reader = PacketReader()
        self.in_flight: dict[int, tuple[int, int, int, float]] = {}
        self.acked = acked  # shared by the worker's connections: (idx, kind, ts, wall, ack)
        self.errors = errors
        self.connacked = asyncio.get_running_loop().create_future()
        self.transport: asyncio.Transport | None = None
        self.closed = False
        self._pid = 0
        self.pending: list[bytes] = []

    def connection_made(self, transport) -> None:
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def data_received(self, data: bytes) -> None:
        try:
            acks = self.reader.feed(data)
        except ProtocolError as exc:
            self.errors.append(str(exc))
            if not self.connacked.done():
                self.connacked.set_exception(exc)
            self.transport.close()
            return
        if self.reader.connacked and not self.connacked.done():
            self.connacked.set_result(True)
        if acks:
            now = time.time()
            in_flight, acked = self.in_flight, self.acked
            for pid in acks:
                sent = in_flight.pop(pid, None)
                if sent is not None:
                    acked.append((*sent, now))

    def connection_lost(self, exc) -> None:
        self.closed = True
        if in_flight := len(self.in_flight):
            self.errors.append(f"connection lost with {in_flight} messages unacknowledged: {exc}")
        if not self.connacked.done():
            self.connacked.set_exception(ConnectionError(f"connection lost: {exc}"))

    def next_pid(self) -> int | None:
        if len(self.in_flight) >= MAX_IN_FLIGHT:
            return None
        pid = self._pid
        while True:
            pid = pid % 0xFFFF + 1
            if pid not in self.in_flight:
                self._pid = pid
                return pid

    def flush(self) -> None:
        if self.pending and not self.closed:
            self.transport.write(b"".join(self.pending))
        self.pending.clear()


def _percentile(values: list[float], q: float) -> float | None:
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


async def _worker(plan: WorkerPlan, pipe: Connection) -> None:
    loop = asyncio.get_running_loop()
    m = len(plan.robot_ids)
    poses = [pose_templates(r, i, c, f"iot/coordinates/{r}")
             for r, i, c in zip(plan.robot_ids, plan.indices, plan.centres)]
    chunk_topics = {t: PublishTemplate(t, b"", b"") for t in set(plan.chunk_topics)}
    chunk_tpl = [chunk_topics[t] for t in plan.chunk_topics]
    robot_bytes = [r.encode() for r in plan.robot_ids]
    rng = random.Random(plan.seed * 1_000_003 + (plan.indices[0] if plan.indices else 0))
    per_chunk = round(plan.chunk_period_s / plan.pose_period_s)
    phases = [chunk_phase(i, per_chunk, plan.aligned_chunks) for i in plan.indices]
    acked: list = []
    errors: list[str] = []
    conns: list[_Connection] = []
    n_conns = m if plan.credentials is not None else max(1, min(plan.connections, m))
    for c in range(n_conns):
        _, conn = await loop.create_connection(lambda: _Connection(acked, errors), plan.host, plan.port)
        user, password = plan.credentials[c] if plan.credentials is not None else (None, None)
        conn.transport.write(connect_packet(f"{plan.client_prefix}-{os.getpid()}-{c}", KEEPALIVE_S,
                                            username=user, password=password))
        conns.append(conn)
    await asyncio.wait_for(asyncio.gather(*(c.connacked for c in conns)), 30)
    conn_of = [conns[j if plan.credentials is not None else j % n_conns] for j in range(m)]
    pipe.send(("ready", os.getpid()))
    message = await loop.run_in_executor(None, pipe.recv)
    if message[0] != "go":
        return
    t0 = message[1]
    cpu0, wall0 = time.process_time(), time.monotonic()
    seconds = plan.seconds if plan.seconds is not None else math.inf
    t_end = t0 + seconds
    period = plan.pose_period_s
    offsets = [i / max(plan.fleet_size, 1) * period for i in plan.indices]
    last_ts = [0] * m
    j = k = 0
    written = [0, 0]
    no_pid = 0
    lags: list[float] = []
    ts_cache_ms, ts_cache = -1, b""
    last_report = last_ping = time.monotonic()
    stopped = False

    def report() -> None:
        if acked:
            idx_kind = array("q", [a[0] * 2 + a[1] for a in acked])
            tss = array("q", [a[2] for a in acked])
            walls = array("d", [a[3] for a in acked])
            ack_walls = array("d", [a[4] for a in acked])
            acked.clear()
            pipe.send(("acked", idx_kind, tss, walls, ack_walls))

    while m and not stopped:
        now = time.monotonic()
        due = t0 + k * period + offsets[j]
        if due <= now:
            wall = time.time()
            now_ms = time.time_ns() // 1_000_000
            while due <= now and due < t_end:
                ts = now_ms if now_ms > last_ts[j] else last_ts[j] + 1
                last_ts[j] = ts
                if ts != ts_cache_ms:
                    ts_cache_ms, ts_cache = ts, format_timestamp(ts).encode()
                conn = conn_of[j]
                pid = conn.next_pid()
                if pid is None:
                    no_pid += 1
                else:
                    conn.pending.append(poses[j][k % POSE_PHASES].packet(pid, ts_cache))
                    conn.in_flight[pid] = (plan.indices[j], POSE, ts, wall)
                    written[POSE] += 1
                    lags.append(now - due)
                    if chunk_follows(k + 1, phases[j], per_chunk):
                        pid = conn.next_pid()
                        if pid is None:
                            no_pid += 1
                        else:
                            payload = chunk_payload(rng.choice(plan.chunk_b64),
                                                    rng.randrange(plan.chunk_rows),
                                                    rng.randrange(plan.chunk_cols), ts_cache,
                                                    robot_bytes[j])
                            conn.pending.append(chunk_tpl[j].packet(pid, payload))
                            conn.in_flight[pid] = (plan.indices[j], CHUNK, ts, wall)
                            written[CHUNK] += 1
                j += 1
                if j == m:
                    j, k = 0, k + 1
                due = t0 + k * period + offsets[j]
            for conn in conns:
                conn.flush()
        if now >= t_end:  # after writing what fell due before the end
            break
        if now - last_report >= REPORT_EVERY_S:
            report()
            last_report = now
            if pipe.poll():
                stopped = pipe.recv()[0] == "stop"
        if now - last_ping >= KEEPALIVE_S / 2:
            for conn in conns:
                conn.transport.write(PINGREQ_PACKET)
            last_ping = now
        if all(c.closed for c in conns):
            break
        # Not to the exact due time of each robot (3,000 wake-ups a second): what falls
        # due within MIN_TICK_S goes out in one write.
        await asyncio.sleep(min(max(due - time.monotonic(), MIN_TICK_S), TICK_S))
    ended = time.monotonic()
    cpu_run = time.process_time() - cpu0
    deadline = ended + plan.ack_wait_s
    while any(c.in_flight and not c.closed for c in conns) and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
        if time.monotonic() - last_report >= REPORT_EVERY_S:
            report()
            last_report = time.monotonic()
    report()
    unacked = sum(len(c.in_flight) for c in conns)
    for conn in conns:
        if not conn.closed:
            conn.transport.write(DISCONNECT_PACKET)
            conn.transport.close()
    run_s = min(ended, t_end) - t0 if ended > t0 else 0.0
    sched = scheduled_messages(plan, max(0.0, run_s)) if plan.seconds is None or stopped \
        else scheduled_messages(plan, seconds)
    pipe.send(("done", {
        "pid": os.getpid(),
        "robots": m,
        "connections": n_conns,
        "scheduled_poses": sched[0],
        "scheduled_chunks": sched[1],
        "written_poses": written[POSE],
        "written_chunks": written[CHUNK],
        "unacknowledged": unacked,
        "no_packet_id": no_pid,
        "lag_p50_s": _percentile(lags, 50),
        "lag_p99_s": _percentile(lags, 99),
        "lag_max_s": max(lags) if lags else None,
        "cpu_s": cpu_run,
        "wall_s": ended - wall0,
        "cpu_percent_of_one_core": 100.0 * cpu_run / max(ended - wall0, 1e-9),
        "errors": errors[:10],
    }))


def worker_main(fd: int) -> None:
    """A worker process's entry point: its plan, then "go", come over the socket `fd`."""
    pipe = Connection(fd)
    plan: WorkerPlan = pipe.recv()
    if plan.nice:
        try:
            os.nice(plan.nice)
        except OSError:
            pass
    try:
        asyncio.run(_worker(plan, pipe))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        try:
            pipe.send(("failed", f"{type(exc).__name__}: {exc}"))
        except OSError:
            pass
        raise


# --- the parent -------------------------------------------------------------------------


class RawFleet:
    """The 2019 workload for `robots` robots from `processes` worker processes.

    `start()` spawns the workers and connects them (they pre-encode their robots' packets
    first); `run(seconds)` starts every worker on one clock and collects what the broker
    acknowledged until they are done. `pids` are the workers' process ids (for CPU
    accounting from outside); `stats.report` holds the schedule and CPU figures."""

    def __init__(self, mqtt_url: str, ros_map, robots: int, *, prefix: str = "robot",
                 processes: int | None = None, connections: int = 2,
                 pose_period_s: float = 1.0, chunk_period_s: float = 5.0, seed: int = 7,
                 mqtt_conn=None, nice: int = 0, ack_wait_s: float = ACK_WAIT_S,
                 aligned_chunks: bool = False) -> None:
        import numpy as np

        from mapservice.adapters.mqtt_client import parse_mqtt_url
        from mapservice.adapters.ros_map import free_cells_metres, meta_for, slice_chunks

        from .connection import RobotMqtt
        from .loadgen import fleet_robot_id

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
            creds = ([(r, self.conn.password(r)) for r in ids] if self.conn.authenticated else None)
            self.plans.append(WorkerPlan(
                host=host, port=port, robot_ids=ids, indices=idx, fleet_size=robots,
                centres=[centres[i] for i in idx], chunk_topics=[self.conn.chunk_topic(r) for r in ids],
                chunk_b64=b64, chunk_rows=meta.chunk_rows, chunk_cols=meta.chunk_cols,
                seconds=None, pose_period_s=pose_period_s, chunk_period_s=chunk_period_s,
                aligned_chunks=aligned_chunks, seed=seed + w, connections=connections,
                credentials=creds, nice=nice, ack_wait_s=ack_wait_s,
                client_prefix=f"rawfleet-{random.Random(seed).getrandbits(32):08x}"))
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
        code = f"from {__name__} import worker_main; import sys; worker_main(int(sys.argv[1]))"
        for plan in self.plans:
            parent, child = socket.socketpair()
            proc = subprocess.Popen([sys.executable, "-c", code, str(child.fileno())],
                                    pass_fds=[child.fileno()])
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

    def run(self, seconds: float | None = None,
            on_tick: Callable[[FleetStats], None] | None = None) -> FleetStats:
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
        self.stats.report = {**summarize(reports),
                             "puback_p50_s": _percentile(self._ack_lags, 50),
                             "puback_p99_s": _percentile(self._ack_lags, 99)}
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
