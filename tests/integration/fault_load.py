"""The load of the fault tests (test_faults.py, test_kafka_cluster_faults.py), and each
fault run under it; their verdict is in fault_verdict.py.

The load: ROBOTS robots publish a pose every POSE_PERIOD_S and a chunk every CHUNK_EVERY
poses through one paho client, at QoS 1; each message's natural identity (robot and
timestamp; row, column, robot and timestamp for a chunk) is recorded with whether the
broker acknowledged it (PUBACK). Each fault gets robots of its own (`<fault>-<n>`), so its
messages are counted apart: published, acknowledged, stored, and the time from the fault
to the first message published after it being queryable through the API."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import clickhouse_connect
import httpx

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.core.wire2019 import (
    content_hash,
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
)

ROBOTS = 10
POSE_PERIOD_S = 0.2  # per robot: 50 poses/s in all
CHUNK_EVERY = 10  # a chunk every 10th pose of a robot: 5 chunks/s
STEADY_S = 1.0  # load before each fault and after its recovery: 50 poses, 5 chunks
DOWN_S = 1.0  # how long a killed component stays down (beyond its own start's time)
CLICKHOUSE_DOWN_S = 30.0
RECOVERY_TIMEOUT_S = 120.0
SNAPSHOT_EVERY_S = 10
SNAPSHOT_ENV = {
    "MAPSERVICE_SNAPSHOT_EVERY_S": str(SNAPSHOT_EVERY_S),
    "MAPSERVICE_SNAPSHOT_GRACE_S": "0",
}  # snapshots every 10 s, built at once
# A killed processors' partitions go to its restart 3 s after it died, not 10.
SHORT_SESSION_ENV = {"MAPSERVICE_KAFKA_SESSION_TIMEOUT_S": "3"}


def now_ms() -> int:
    return time.time_ns() // 1_000_000


@dataclass
class Sent:
    kind: str  # "pose" or "chunk"
    key: tuple  # pose: (robot, ts_ms); chunk: (row, column, robot, ts_ms)
    segment: str
    sent_ms: int
    content_hash: str = ""
    acknowledged: bool = False  # the broker sent PUBACK for it


class Load:
    """Robots publishing poses and chunks at QoS 1 through one paho client (clean session:
    what it published and the broker acknowledged is the broker's to keep), on a fixed
    schedule; `segment` names the robots, so each fault's messages are its own."""

    def __init__(self, mqtt_url: str, meta) -> None:
        self.meta = meta
        host, port, _ = parse_mqtt_url(mqtt_url)
        self.client = make_client(f"faults-load-{os.getpid()}")
        self.client.reconnect_delay_set(0.1, 1)  # back quickly after the broker restarts
        # PUBACKs by packet id; an id is reused only after its PUBACK. (paho's
        # MQTTMessageInfo cannot say it: one published while disconnected keeps rc
        # NO_CONN after it was sent and acknowledged.)
        self.client.on_publish = self._on_publish
        self._in_flight: dict[int, Sent] = {}
        self._early: set[int] = set()
        self.sent: list[Sent] = []
        self.segment = "warmup"
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.client.connect(host, port, keepalive=10)
        self.client.loop_start()
        size = meta.chunk_width * meta.chunk_height
        self.shades = [(bytes([s]) * size) for s in (0, 100, 205, 254)]
        self.hashes = [content_hash(p).hex() for p in self.shades]
        self.thread = threading.Thread(target=self._run, name="faults-load", daemon=True)
        self.thread.start()

    def _on_publish(self, _client, _userdata, mid, _reason_code, _properties) -> None:
        # paho calls this holding its own message lock: take ours only briefly, never
        # around publish() (that would be a lock-order deadlock).
        with self._lock:
            sent = self._in_flight.pop(mid, None)
            if sent is None:
                self._early.add(mid)  # the PUBACK beat the registration below
        if sent is not None:
            sent.acknowledged = True

    def _publish(
        self, kind: str, segment: str, topic: str, payload: bytes, key: tuple, content: str = ""
    ) -> None:
        sent = Sent(kind, key, segment, now_ms(), content)
        info = self.client.publish(topic, payload, qos=1)
        with self._lock:
            self.sent.append(sent)
            if info.mid in self._early:
                self._early.discard(info.mid)
                sent.acknowledged = True
            else:
                self._in_flight[info.mid] = sent

    def _run(self) -> None:
        n, k = 0, 0
        last_ts: dict[str, int] = {}
        next_at = time.monotonic()
        while not self._stop.is_set():
            next_at += POSE_PERIOD_S / ROBOTS
            self._stop.wait(max(0.0, next_at - time.monotonic()))
            i = n % ROBOTS
            # Read once per tick: the test switches segments from its own thread, and a
            # message counted in one segment under another segment's robot is looked for
            # among the wrong robots by that segment's wait (never found: "not caught up").
            segment = self.segment
            robot = f"{segment}-{i}"
            ts = max(now_ms(), last_ts.get(robot, 0) + 1)
            last_ts[robot] = ts
            self._publish(
                "pose",
                segment,
                f"iot/coordinates/{robot}",
                encode_coordinates(
                    robot,
                    format_timestamp(ts),
                    1.0 + i,
                    2.0 + (ts % 1000) / 1000,
                    battery_level=50.0,
                ),
                (robot, ts),
            )
            if (n // ROBOTS) % CHUNK_EVERY == 0:
                row, col = (
                    k % self.meta.chunk_rows,
                    (k // self.meta.chunk_rows) % self.meta.chunk_cols,
                )
                shade = k % len(self.shades)
                self._publish(
                    "chunk",
                    segment,
                    "iot/chunks/create",
                    encode_chunk_create(row, col, self.shades[shade], format_timestamp(ts), robot),
                    (row, col, robot, ts),
                    self.hashes[shade],
                )
                k += 1
            n += 1

    def stop(self, ack_timeout_s: float = 60) -> None:
        """Stops publishing; waits (bounded) for the broker to acknowledge what is pending."""
        self._stop.set()
        self.thread.join(10)
        deadline = time.monotonic() + ack_timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if not self._in_flight:
                    return
            time.sleep(0.1)

    def close(self) -> None:
        self._stop.set()
        self.client.loop_stop()
        self.client.disconnect()

    def of(self, segment: str) -> list[Sent]:
        with self._lock:
            return [s for s in self.sent if s.segment == segment]


@dataclass
class FaultRun:
    name: str
    killed_ms: int = 0
    restarted_ms: int = 0  # the component (or ClickHouse) is back and ready
    recovered_ms: int | None = None  # the first message published after the fault is queryable
    caught_up_ms: int | None = None  # every acknowledged message of the fault's robots stored


def run_fault(name: str, load: Load, api_url: str, sql: Sql, fault: Callable[[], None]) -> FaultRun:
    """Load on this fault's own robots, then `fault()` (kill, stay down, restart: it returns
    once the part is back), then wait until a message published after the kill is
    queryable, and until the backlog is stored (so the next fault starts clean: a Kafka
    kill right after a ClickHouse outage would lose the outage's backlog, and count it
    against the outage)."""
    run = FaultRun(name)
    load.segment = name
    time.sleep(STEADY_S)
    run.killed_ms = now_ms()
    fault()
    run.restarted_ms = now_ms()
    deadline = time.monotonic() + RECOVERY_TIMEOUT_S
    while time.monotonic() < deadline:
        if queryable(api_url, f"{name}-0", run.killed_ms + 1):
            run.recovered_ms = now_ms()
            break
        time.sleep(0.2)
    run.caught_up_ms = wait_caught_up(sql, load, name)
    print(
        f"{name}: back after {(run.restarted_ms - run.killed_ms) / 1000:.1f} s, queryable after "
        f"{((run.recovered_ms or now_ms()) - run.killed_ms) / 1000:.1f} s, caught up after "
        + (
            f"{(run.caught_up_ms - run.killed_ms) / 1000:.1f} s"
            if run.caught_up_ms
            else "- (never: lost)"
        ),
        flush=True,
    )
    return run


def wait_caught_up(
    sql: Sql, load: Load, segment: str, timeout_s: float = 90, stalled_s: float = 10
) -> int | None:
    """Until every acknowledged message of `segment` published over a second ago is stored
    (when; None if none of the missing ones got stored for `stalled_s`: lost, or timeout)."""
    deadline = time.monotonic() + timeout_s
    missing: set = set()
    progress = time.monotonic()
    while time.monotonic() < deadline:
        cutoff = now_ms() - 1000
        want = {s.key for s in load.of(segment) if s.acknowledged and s.sent_ms <= cutoff}
        try:
            poses, chunks = stored_identities(sql, [segment], final=True)
        except Exception:  # noqa: BLE001 - the server may be coming back: ask again
            time.sleep(0.5)
            continue
        now_missing = want - set(poses) - set(chunks)
        if not now_missing:
            return now_ms()
        if missing - now_missing:  # some that were missing got stored
            progress = time.monotonic()
        elif time.monotonic() - progress >= stalled_s:
            _print_missing(load, segment, now_missing)
            return None
        missing = now_missing
        time.sleep(0.5)
    _print_missing(load, segment, missing)
    return None


def _print_missing(load: Load, segment: str, missing: set) -> None:
    """Which acknowledged messages were still not stored when the wait gave up, oldest
    first, with when each was sent: a verdict of "never caught up" then says whether the
    stragglers were sent before the fault, during it or after it."""
    sent = {s.key: s for s in load.of(segment)}
    oldest = sorted(missing, key=lambda k: sent[k].sent_ms)[:10]
    print(
        f"{segment}: {len(missing)} acknowledged message(s) not stored at {now_ms()}; oldest: "
        + ", ".join(f"{k} sent {sent[k].sent_ms}" for k in oldest),
        flush=True,
    )


def queryable(api_url: str, robot: str, from_ms: int) -> bool:
    """Whether the API returns a pose of `robot` at or after `from_ms` (any error: no)."""
    try:
        reply = httpx.get(
            f"{api_url}/api/v1/poses",
            timeout=5,
            params={"robotId": robot, "from": from_ms, "to": from_ms + 600_000, "limit": 1},
        )
        return reply.status_code == 200 and bool(reply.json())
    except httpx.HTTPError:
        return False


class Sql:
    """Statements on the stack's ClickHouse: the server itself (split) or, under `up`, the
    API's read-only analyst endpoint (chDB is `serve`'s alone)."""

    def __init__(self, **client_args) -> None:
        self.client_args = client_args
        self._client = None  # one connection for every statement, new after a failure

    def __call__(self, query: str, **parameters) -> list[tuple]:
        if self._client is None:
            self._client = clickhouse_connect.get_client(
                connect_timeout=10, send_receive_timeout=60, **self.client_args
            )
        try:
            if query.startswith("OPTIMIZE"):
                self._client.command(query)
                return []
            return self._client.query(query, parameters=parameters).result_rows
        except Exception:
            # The server may have been restarted: the next statement connects anew.
            self.close()
            raise

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


def stored_identities(sql: Sql, segments: list[str], final: bool) -> tuple[dict, dict]:
    """Rows per natural identity of the test's robots, raw (as stored) or FINAL (as every
    read sees them): poses (robot, ts) -> n, chunk writes (row, col, robot, ts) -> (n, hash)."""
    where = " OR ".join(f"startsWith(robot_id, '{s}-')" for s in segments)
    f = " FINAL" if final else ""
    poses = {
        (r, t): n
        for r, t, n in sql(
            f"SELECT robot_id, toUnixTimestamp64Milli(ts), count() FROM mapservice.poses{f} "
            f"WHERE {where} GROUP BY 1, 2"
        )
    }
    chunks = {
        (row, col, r, t): (n, h)
        for row, col, r, t, n, h in sql(
            "SELECT row, col, robot_id, toUnixTimestamp64Milli(ts), count(), "
            f"lower(hex(any(content_hash))) FROM mapservice.chunk_events{f} WHERE {where} "
            "GROUP BY 1, 2, 3, 4"
        )
    }
    return poses, chunks
