"""A RawFleet worker process: an asyncio loop that connects its robots, writes their
pre-encoded PUBLISH packets as they fall due, matches the PUBACKs and streams what the
broker acknowledged back to the parent (rawfleet.py) over a socket."""

from __future__ import annotations

import asyncio
import math
import os
import random
import socket
import time
from array import array
from multiprocessing.connection import Connection

from mapservice.bench.fleet.mqtt_packets import (
    DISCONNECT_PACKET,
    PINGREQ_PACKET,
    PacketReader,
    ProtocolError,
    PublishTemplate,
    connect_packet,
)
from mapservice.bench.fleet.rawfleet_plan import (
    CHUNK,
    KEEPALIVE_S,
    MAX_IN_FLIGHT,
    MIN_TICK_S,
    POSE,
    POSE_PHASES,
    REPORT_EVERY_S,
    TICK_S,
    WorkerPlan,
    chunk_payload,
    percentile,
    pose_templates,
    scheduled_messages,
)
from mapservice.core.wire2019 import format_timestamp
from mapservice.robot.schedule import chunk_follows, chunk_phase


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


async def _worker(plan: WorkerPlan, pipe: Connection) -> None:
    loop = asyncio.get_running_loop()
    m = len(plan.robot_ids)
    poses = [
        pose_templates(r, i, c, f"iot/coordinates/{r}")
        for r, i, c in zip(plan.robot_ids, plan.indices, plan.centres)
    ]
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
        _, conn = await loop.create_connection(
            lambda: _Connection(acked, errors), plan.host, plan.port
        )
        user, password = plan.credentials[c] if plan.credentials is not None else (None, None)
        conn.transport.write(
            connect_packet(
                f"{plan.client_prefix}-{os.getpid()}-{c}",
                KEEPALIVE_S,
                username=user,
                password=password,
            )
        )
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
                            payload = chunk_payload(
                                rng.choice(plan.chunk_b64),
                                rng.randrange(plan.chunk_rows),
                                rng.randrange(plan.chunk_cols),
                                ts_cache,
                                robot_bytes[j],
                            )
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
    sched = (
        scheduled_messages(plan, max(0.0, run_s))
        if plan.seconds is None or stopped
        else scheduled_messages(plan, seconds)
    )
    pipe.send(
        (
            "done",
            {
                "pid": os.getpid(),
                "robots": m,
                "connections": n_conns,
                "scheduled_poses": sched[0],
                "scheduled_chunks": sched[1],
                "written_poses": written[POSE],
                "written_chunks": written[CHUNK],
                "unacknowledged": unacked,
                "no_packet_id": no_pid,
                "lag_p50_s": percentile(lags, 50),
                "lag_p99_s": percentile(lags, 99),
                "lag_max_s": max(lags) if lags else None,
                "cpu_s": cpu_run,
                "wall_s": ended - wall0,
                "cpu_percent_of_one_core": 100.0 * cpu_run / max(ended - wall0, 1e-9),
                "errors": errors[:10],
            },
        )
    )


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
