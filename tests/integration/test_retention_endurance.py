"""Endurance on a simulated clock through the real pipeline (Mosquitto, gateway, tansu,
processors with their snapshot, repair and retention timers, API, chDB): six simulated
days with a retention of two (three retention periods) in about three real minutes.
Robots publish poses over MQTT at QoS 1, the floor is published once at the start and a
pallet moves every six simulated hours; the processors and the gateway are restarted
along the way. At the end, many instants of the retention are read through the API and
checked against a brute-force fold of everything acknowledged: the map at T, the 2019
`latest=true&updatedBefore=T` listing with its pixels, the robots at T; then, with the
stack stopped, no snapshot names missing pixels and the days before the retention are
gone. (Storage per simulated day is measured by tests/mapservice/adapters/test_store_retention.py.)
"""

from __future__ import annotations

import base64
import time
import zlib

import httpx
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.adapters.ros_map import load_ros_map, meta_for, slice_chunks
from mapservice.core.timetravel import fold_map
from mapservice.core.wire2019 import content_hash, encode_chunk_create, encode_coordinates, format_timestamp
from tests.fixtures.paths import MAPS

from .conftest import start_stack

DAY = 86_400_000
HOUR = 3_600_000
RATE = 2880  # a simulated day every 30 real seconds
RETENTION_DAYS = 2
SIM_DAYS = 6
ROBOTS = ("end-1", "end-2", "end-3")


class SimClock:
    def __init__(self, start_ms: int, origin_ms: int) -> None:
        self.start_ms, self.origin_ms = start_ms, origin_ms

    def now_ms(self) -> int:
        return self.start_ms + (time.time_ns() // 1_000_000 - self.origin_ms) * RATE


class Write:
    def __init__(self, row, column, ts_ms, robot_id, pixels) -> None:
        self.row, self.column, self.ts_ms, self.robot_id = row, column, ts_ms, robot_id
        self.pixels, self.content_hash = pixels, content_hash(pixels).hex()


@pytest.fixture(scope="module")
def sim_stack(tmp_path_factory):
    real_now = time.time_ns() // 1_000_000
    origin = real_now + 20_000  # the stack takes a while to start: the clock starts then
    start = real_now - 30 * DAY  # far in the past: no real clock can expire anything
    env = {"MAPSERVICE_CLOCK_START": str(start), "MAPSERVICE_CLOCK_ORIGIN": str(origin),
           "MAPSERVICE_CLOCK_RATE": str(RATE), "MAPSERVICE_RETENTION_DAYS": str(RETENTION_DAYS),
           "MAPSERVICE_SNAPSHOT_EVERY_S": "10800", "MAPSERVICE_SNAPSHOT_GRACE_S": "600",
           "MAPSERVICE_MAX_FUTURE_SKEW_S": "7200"}
    stack = start_stack(tmp_path_factory, "mosquitto", env)
    yield stack, SimClock(start, origin)
    stack.stop()


def test_three_retention_periods_through_the_pipeline(sim_stack) -> None:
    stack, clock = sim_stack
    while clock.now_ms() < clock.start_ms:
        time.sleep(0.1)
    depot = load_ros_map(MAPS / "depot.yaml")
    floor = slice_chunks(depot)
    meta = meta_for(depot)
    host, port, _ = parse_mqtt_url(stack.mqtt_url)
    client = make_client(f"endurance-{time.time_ns()}")
    client.connect(host, port)
    client.loop_start()
    written: list[Write] = []
    last_pose: dict[str, int] = {}
    pending = []

    def publish(topic: str, payload: bytes) -> None:
        pending.append(client.publish(topic, payload, qos=1))

    t0 = clock.now_ms()
    for (row, column), pixels in sorted(floor.items()):
        written.append(Write(row, column, t0, "mapper", pixels))
        publish("iot/chunks/create", encode_chunk_create(row, column, pixels, format_timestamp(t0), "mapper"))
    end = t0 + SIM_DAYS * DAY
    next_change, changes, restarted = t0 + 6 * HOUR, 0, set()
    pallet = (meta.chunk_rows // 2, meta.chunk_cols // 2)
    try:
        while (now := clock.now_ms()) < end:
            for i, robot in enumerate(ROBOTS):
                ts = now - i
                publish(f"iot/coordinates/{robot}", encode_coordinates(
                    robot, format_timestamp(ts), 1.0 + i, 2.0, battery_level=50.0))
                last_pose[robot] = max(last_pose.get(robot, 0), ts)
            if now >= next_change:
                changes += 1
                pixels = bytes([changes % 200 + 20]) * (meta.chunk_width * meta.chunk_height)
                written.append(Write(*pallet, now, ROBOTS[changes % 3], pixels))
                publish("iot/chunks/create", encode_chunk_create(*pallet, pixels, format_timestamp(now),
                                                                 ROBOTS[changes % 3]))
                next_change += 6 * HOUR
            day = (now - t0) / DAY
            if day > 2.5 and "server" not in restarted:
                restarted.add("server")
                stack.restart("server")  # processors and API: the timers stop and resume
            if day > 4.2 and "gateway" not in restarted:
                restarted.add("gateway")
                stack.restart("gateway")  # QoS 1 messages wait in Mosquitto meanwhile
            for info in pending:
                info.wait_for_publish(30)
                assert info.is_published(), "a QoS 1 publish was not acknowledged"
            pending.clear()
            time.sleep(0.2)
    finally:
        client.loop_stop()
        client.disconnect()

    api = httpx.Client(base_url=stack.api_url, timeout=30)

    def get(path: str, **params):
        r = api.get(path, params=params)
        assert r.status_code == 200, r.text
        return r.json()

    # Everything acknowledged reaches the history (the gateway had a backlog after its restart).
    deadline = time.monotonic() + 90
    while True:
        seen = {r["robotId"]: r["ts_ms"] for r in get("/api/v1/robots")["robots"]}
        if all(seen.get(r) == last_pose[r] for r in ROBOTS) or time.monotonic() > deadline:
            break
        time.sleep(1)
    assert {r: seen.get(r) for r in ROBOTS} == last_pose

    checked = 0
    for fraction in (0.02, 0.1, 0.25, 0.4, 0.55, 0.7, 0.85, 0.97):
        now = clock.now_ms()
        t = now - RETENTION_DAYS * DAY + int(fraction * RETENTION_DAYS * DAY)
        want = fold_map(written, t)
        got = get("/api/v1/map", at=str(t))["chunks"]
        assert {(c["row"], c["column"]): c["content_hash"] for c in got} == {
            k: v.content_hash for k, v in want.items()}, f"map {fraction:.0%} into the retention"
        listing = get("/api/chunk-service/chunks", latest="true", updatedBefore=str(t + 1), limit="10000")
        pixels = {(w.row, w.column, w.content_hash): w.pixels for w in written}
        assert len(listing) == len(want) == len(floor)
        for doc in listing:
            w = want[(doc["row"], doc["column"])]
            assert doc["chunk"] is not None, "the 2019 listing names pixels that are gone"
            assert zlib.decompress(base64.b64decode(doc["chunk"])) == pixels[(w.row, w.column, w.content_hash)]
        robots = {r["robotId"] for r in get("/api/v1/robots", at=str(t))["robots"]}
        assert set(ROBOTS) <= robots
        checked += 1
    assert checked == 8
    api.close()
    stack.stop()

    store = ClickHouseStore.from_settings(stack.settings())
    try:
        db = store.database
        missing = store._rows(f"SELECT count() FROM {db}.map_snapshots WHERE content_hash NOT IN "
                              f"(SELECT content_hash FROM {db}.chunk_contents)", {})[0][0]
        assert missing == 0, "a snapshot names pixels that are gone"
        (oldest,), = store._rows(f"SELECT toUnixTimestamp64Milli(min(ts)) FROM {db}.chunk_events", {})
        assert oldest >= end - (RETENTION_DAYS + 1) * DAY, "days before the retention were kept"
    finally:
        store.close()
