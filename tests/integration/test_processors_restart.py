"""Killing the processors mid-stream and restarting them (Apache Kafka, Mosquitto, chDB): no
duplicate history, correct snapshots and conflicts, and the latest-map view rebuilt so
advertisements resume without letting older writes win."""

from __future__ import annotations

import os
import random
import signal
import threading
import time
import zlib

import httpx
import msgspec
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.adapters.mqtt_client import make_client
from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.core.conflicts import all_conflicts
from mapservice.core.events import (
    ChunkUpdated,
    Envelope,
    PoseReported,
    encode,
    kafka_key,
    make_envelope,
)
from mapservice.core.ports import ChunkRow
from mapservice.core.timetravel import fold_map
from mapservice.core.wire2019 import content_hash, parse_timestamp
from mapservice.local.stack import Stack
from tests.fixtures.paths import MAPS

ROBOTS = ["r1", "r2", "r3", "r4"]
CHUNKS = [(r, c) for r in range(3) for c in range(2)]
WINDOW_MS = 60_000
# The snapshot timer's period (a quarter of the 20 s snapshot interval, 5 s, by default):
# a short one lets the waits for "a tick has run" be short too.
SNAPSHOT_TICK_S = 1.0
# Long enough that a whole tick ran after it began (one may be just under way).
A_WHOLE_TICK_S = 3 * SNAPSHOT_TICK_S


def chunk(robot: str, ts: int, row: int, col: int, shade: int) -> Envelope:
    pixels = bytes([shade]) * 10_000
    payload = ChunkUpdated(row, col, 100, 100, zlib.compress(pixels), content_hash(pixels))
    return make_envelope(robot, ts, ts + 30, payload)


def pose(robot: str, ts: int) -> Envelope:
    return make_envelope(
        robot, ts, ts + 20, PoseReported((ts % 1000 / 10, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0), 50.0)
    )


def writes(rng: random.Random, n: int, lo: int, hi: int) -> list[Envelope]:
    return [
        chunk(
            rng.choice(ROBOTS),
            rng.randrange(lo, hi) // 10 * 10,
            *rng.choice(CHUNKS),
            rng.choice([10, 20, 30]),
        )
        for _ in range(n)
    ]


def poses(lo: int, hi: int) -> list[Envelope]:
    return [pose(r, t) for t in range(lo, hi, 10_000) for r in ROBOTS]


def publish(stack: Stack, events: list[Envelope]) -> None:
    settings = stack.settings()
    publisher = KafkaPublisher(settings, client_id="restart-test")
    errors: list = []
    for e in events:
        topic = (
            settings.topic_chunk_events
            if isinstance(e.payload, ChunkUpdated)
            else settings.topic_pose_events
        )
        publisher.publish(topic, kafka_key(e), encode(e), lambda err: err and errors.append(err))
    assert publisher.flush(30) == 0 and not errors


def row(e: Envelope) -> ChunkRow:
    p = e.payload
    return ChunkRow(
        p.row, p.column, e.event_time_ms, e.robot_id, p.content_hash.hex(), e.receive_time_ms
    )


class Advertisements:
    """Every advertisement on the topic, in arrival order."""

    def __init__(self, url: str, topic: str) -> None:
        host, port = url.removeprefix("mqtt://").split(":")
        self.received: list[dict] = []
        self.subscribed = threading.Event()
        self.client = make_client(f"restart-test-{os.getpid()}")
        self.client.on_connect = lambda c, *a: c.subscribe(topic, qos=1)
        self.client.on_subscribe = lambda *a: self.subscribed.set()
        self.client.on_message = lambda c, u, m: self.received.append(
            msgspec.json.decode(m.payload)
        )
        self.client.connect(host, int(port))
        self.client.loop_start()
        assert self.subscribed.wait(10)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def api(stack: Stack, path: str, **params):
    r = httpx.get(f"{stack.api_url}{path}", params=params, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def wait_stored(stack: Stack, lo: int, hi: int, chunks: int, pose_count: int, timeout_s=90) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = (
            len(api(stack, "/api/v1/chunk-events", **{"from": lo, "to": hi, "limit": 100_000})),
            len(api(stack, "/api/v1/poses", **{"from": lo, "to": hi, "limit": 100_000})),
        )
        if got == (chunks, pose_count):
            return
        time.sleep(0.5)
    raise AssertionError(f"stored {got}, expected {(chunks, pose_count)}")


def kill_server(stack: Stack) -> None:
    proc = stack.procs.pop("server")
    os.killpg(proc.pid, signal.SIGKILL)  # no clean shutdown: offsets stay uncommitted
    proc.wait(30)


@pytest.fixture
def stack(tmp_path):
    s = Stack(
        tmp_path / "restart",
        mqtt="mosquitto",
        extra_env={
            "MAPSERVICE_SNAPSHOT_EVERY_S": "20",
            "MAPSERVICE_SNAPSHOT_GRACE_S": "0",
            "MAPSERVICE_SNAPSHOT_TICK_S": str(SNAPSHOT_TICK_S),
            "MAPSERVICE_CONFLICT_WINDOW_S": str(WINDOW_MS // 1000),
            # The killed server's partitions go to its restart 3 s after it died, not 10.
            "MAPSERVICE_KAFKA_SESSION_TIMEOUT_S": "3",
        },
    )
    s.extra_env["MAPSERVICE_PUBLIC_BASE_URL"] = s.api_url
    try:
        s.start_brokers()
        s.publish_meta(meta_for(load_ros_map(MAPS / "depot.yaml")))
        s.start_server()
        yield s
    finally:
        s.stop()


def test_restart_mid_stream_rebuilds_views_without_duplicates_or_wrong_snapshots(stack) -> None:
    """Kill -9 mid-stream, restart, re-deliver and send late writes: history, snapshots,
    conflicts and advertisements are exactly what a fold of the unique events gives."""
    rng = random.Random(3)
    now = time.time_ns() // 1_000_000
    base = now // 1000 * 1000 - 15 * 60_000
    minute = 60_000
    ads = Advertisements(stack.mqtt_url, "iot/chunks/advertisement")
    try:
        phase1 = writes(rng, 30, base, base + 5 * minute) + poses(base, base + 5 * minute)
        publish(stack, phase1)
        unique = {e.event_id: e for e in phase1}
        n_chunks = lambda: sum(isinstance(e.payload, ChunkUpdated) for e in unique.values())  # noqa: E731
        n_poses = lambda: len(unique) - n_chunks()  # noqa: E731
        wait_stored(stack, base, base + 13 * minute, n_chunks(), n_poses())
        time.sleep(A_WHOLE_TICK_S)  # snapshots built: the late writes below must repair them

        phase2 = writes(rng, 30, base + 5 * minute, base + 10 * minute) + poses(
            base + 5 * minute, base + 10 * minute
        )
        publish(stack, phase2)
        unique.update({e.event_id: e for e in phase2})
        wait_stored(stack, base, base + 13 * minute, n_chunks(), n_poses())
        time.sleep(2)  # offsets committed: these are not re-delivered after the kill

        # Mid-stream: writes to two chunks only, killed while they are being taken in.
        in_flight = [
            chunk(rng.choice(ROBOTS), base + 10 * minute + i * 3000 + 7, *CHUNKS[i % 2], 60)
            for i in range(10)
        ] + poses(base + 10 * minute, base + 10 * minute + 30_000)
        publish(stack, in_flight)
        time.sleep(0.3)
        kill_server(stack)
        unique.update({e.event_id: e for e in in_flight})
        before_restart = len(ads.received)
        assert before_restart > 0

        stack.start_server()
        live = fold_map(
            [row(e) for e in unique.values() if isinstance(e.payload, ChunkUpdated)], 2**62
        )
        # Re-delivered writes and late ones, all older than the live version of their chunk:
        # history, never advertised (an empty view after the restart would advertise them).
        # (The late ones' times end in 5 ms: no identity of theirs exists already.)
        late = [
            chunk(r, max(base, live[(rw, c)].ts_ms - 1000 * rng.randrange(1, 200)) + 5, rw, c, 40)
            for r, (rw, c) in zip(ROBOTS * 2, CHUNKS)
        ]
        older = phase1[:20] + phase2 + late + poses(base + 10 * minute + 30_000, base + 11 * minute)
        rng.shuffle(older)
        publish(stack, older)
        unique.update({e.event_id: e for e in older})
        wait_stored(stack, base, base + 13 * minute, n_chunks(), n_poses())
        time.sleep(2)
        in_flight_ids = {
            (e.payload.row, e.payload.column, e.event_time_ms, e.robot_id)
            for e in in_flight
            if isinstance(e.payload, ChunkUpdated)
        }
        for a in ads.received[before_restart:]:
            assert (
                a["row"],
                a["column"],
                parse_timestamp(a["timestamp"]),
                a["robotId"],
            ) in in_flight_ids, a

        newest = [
            chunk(rng.choice(ROBOTS), base + 11 * minute + i * 1000, rw, c, 50 + i)
            for i, (rw, c) in enumerate(CHUNKS)
        ]
        last = newest + poses(base + 11 * minute, base + 12 * minute)
        publish(stack, last)
        unique.update({e.event_id: e for e in last})
        wait_stored(stack, base, base + 13 * minute, n_chunks(), n_poses())
        time.sleep(A_WHOLE_TICK_S)  # a snapshot tick after the last batch

        chunk_rows = [row(e) for e in unique.values() if isinstance(e.payload, ChunkUpdated)]
        stored = api(
            stack,
            "/api/v1/chunk-events",
            **{"from": base, "to": base + 13 * minute, "limit": 100_000},
        )
        keys = [(c["row"], c["column"], c["ts_ms"], c["robotId"]) for c in stored]
        assert len(keys) == len(set(keys)) == len(chunk_rows)

        probes = [
            base - 1,
            base + 2 * minute,
            base + 5 * minute,
            base + 7 * minute + 333,
            base + 10 * minute,
            base + 11 * minute + 2500,
            now,
        ] + [e.event_time_ms for e in late]
        for t in probes:
            got = {
                (c["row"], c["column"]): (c["ts_ms"], c["robotId"], c["content_hash"])
                for c in api(stack, "/api/v1/map", at=t)["chunks"]
            }
            want = {
                k: (s.ts_ms, s.robot_id, s.content_hash) for k, s in fold_map(chunk_rows, t).items()
            }
            assert got == want, t
            robots = {
                r["robotId"]: r["ts_ms"] for r in api(stack, "/api/v1/robots", at=t)["robots"]
            }
            pose_rows = [e for e in unique.values() if isinstance(e.payload, PoseReported)]
            latest: dict = {}
            for e in pose_rows:
                if e.event_time_ms <= t:
                    latest[e.robot_id] = max(
                        latest.get(e.robot_id, e.event_time_ms), e.event_time_ms
                    )
            assert robots == latest, t

        got_conflicts = api(
            stack, "/api/v1/conflicts", **{"from": base - minute, "to": base + 14 * minute}
        )["conflicts"]
        assert got_conflicts  # the workload has some, so the comparison means something
        fields = ("row", "column", "ts_ms", "robot_a", "ts_a_ms", "robot_b")
        assert [tuple(c[f] for f in fields) for c in got_conflicts] == [
            tuple(msgspec.structs.astuple(c)) for c in all_conflicts(chunk_rows, WINDOW_MS)
        ]
        hashes = {(w.row, w.column, w.ts_ms, w.robot_id): w.content_hash for w in chunk_rows}
        assert [(c["hash_a"], c["hash_b"]) for c in got_conflicts] == [
            (
                hashes[c["row"], c["column"], c["ts_a_ms"], c["robot_a"]],
                hashes[c["row"], c["column"], c["ts_ms"], c["robot_b"]],
            )
            for c in got_conflicts
        ]

        final = fold_map(chunk_rows, 2**62)
        want_last = {k: (s.ts_ms, s.robot_id) for k, s in final.items()}
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            got_last = {
                (a["row"], a["column"]): (parse_timestamp(a["timestamp"]), a["robotId"])
                for a in ads.received
            }
            if got_last == want_last:
                break
            time.sleep(0.5)
        by_identity = {(r.row, r.column, r.ts_ms, r.robot_id) for r in chunk_rows}
        seen: dict = {}
        for a in ads.received:
            k = (a["row"], a["column"])
            order = (parse_timestamp(a["timestamp"]), a["robotId"])
            assert (*k, *order) in by_identity
            assert k not in seen or order > seen[k], (k, order, seen.get(k))  # older never wins
            seen[k] = order
        assert len(ads.received) > before_restart  # advertising resumed after the restart
        assert seen == want_last
        for k, s in final.items():
            a = [x for x in ads.received if (x["row"], x["column"]) == k][-1]
            doc = httpx.get(a["chunkUrl"], timeout=30).json()
            assert (doc["robotId"], doc["row"], doc["column"]) == (s.robot_id, *k)
    finally:
        ads.close()

    # The processors are gone: open the history directly and check the snapshots.
    stack.stop()
    store = ClickHouseStore(f"chdb://{stack.data_dir / 'clickhouse'}")
    try:
        (n_snaps,) = store.client.query(
            "SELECT count() FROM mapservice.snapshot_log FINAL WHERE snap_ts >= "
            "fromUnixTimestamp64Milli({b:Int64})",
            parameters={"b": base},
        ).result_rows[0]
        assert n_snaps >= 30
        for t in range(base, base + 13 * minute, 20_000):
            assert {(c.row, c.column): c for c in store.map_at(t)} == fold_map(chunk_rows, t), t
        assert store.counts().chunk_events == len(chunk_rows)
    finally:
        store.close()
