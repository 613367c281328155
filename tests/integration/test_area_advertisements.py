"""Per-area advertisements through the whole stack (gateway, Kafka, processors, Mosquitto):
a robot writes every chunk of the map; a subscriber to an area's topic receives exactly the
changes of that area's chunks, each area topic carries only its own chunks, and the 2019
topic still receives every change."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict

import pytest

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.adapters.ros_map import load_ros_map, slice_chunks
from mapservice.core.areas import AreaGrid, area_topic, area_topic_filter
from mapservice.core.wire2019 import encode_chunk_create, format_timestamp
from mapservice.local.stack import Stack
from tests.fixtures.paths import MAPS

from .conftest import start_stack
from .test_pipeline import now_ms, publish_all

ADS = "iot/chunks/advertisement"
AREA_CHUNKS = 2  # the depot map's 4 x 7 chunks in 2 x 4 areas, the last ones partial


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = start_stack(
        tmp_path_factory,
        "mosquitto",
        extra_env={"MAPSERVICE_ADVERTISEMENT_AREA_CHUNKS": str(AREA_CHUNKS)},
    )
    yield stack
    stack.stop()


class Listener:
    """One connection reading some filters, keeping (topic, row, column) of each message."""

    def __init__(self, stack: Stack, filters: list[str]) -> None:
        host, port, _ = parse_mqtt_url(stack.mqtt_url)
        self.got: list[tuple[str, int, int]] = []
        self._lock = threading.Lock()
        acked = threading.Semaphore(0)
        self.client = make_client(f"area-listener-{time.time_ns()}")
        self.client.on_message = self._message
        self.client.on_subscribe = lambda *_args: acked.release()
        self.client.connect(host, port)
        self.client.loop_start()
        for f in filters:
            self.client.subscribe(f, qos=1)
        for f in filters:
            assert acked.acquire(timeout=10), f"no SUBACK for {f}"

    def _message(self, _client, _userdata, msg) -> None:
        doc = json.loads(msg.payload)
        with self._lock:
            self.got.append((msg.topic, doc["row"], doc["column"]))

    def chunks(self) -> set[tuple[int, int]]:
        with self._lock:
            return {(r, c) for _t, r, c in self.got}

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def test_an_area_topic_carries_exactly_its_areas_changes_and_the_2019_topic_all(stack) -> None:
    grid = AreaGrid(AREA_CHUNKS)
    chunks = slice_chunks(load_ros_map(MAPS / "depot.yaml"))
    areas = sorted({grid.area_of_chunk(r, c) for r, c in chunks})
    assert len(areas) == 8
    plant = Listener(stack, [ADS])
    every_area = Listener(stack, [area_topic_filter(ADS)])
    one_each = {area: Listener(stack, [area_topic(ADS, area)]) for area in areas}
    try:
        t0 = now_ms() - 5_000
        publish_all(
            stack,
            [
                (
                    "iot/chunks/create",
                    encode_chunk_create(r, c, px, format_timestamp(t0 + i), "area-robot"),
                )
                for i, ((r, c), px) in enumerate(sorted(chunks.items()))
            ],
        )
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (
            plant.chunks() != set(chunks) or every_area.chunks() != set(chunks)
        ):
            time.sleep(0.2)
        time.sleep(1.0)  # nothing more arrives: no duplicate, no stray
        assert sorted((r, c) for _t, r, c in plant.got) == sorted(chunks)
        assert {t for t, _r, _c in plant.got} == {ADS}
        assert sorted((r, c) for _t, r, c in every_area.got) == sorted(chunks)
        for topic, r, c in every_area.got:
            assert topic == area_topic(ADS, grid.area_of_chunk(r, c))
        by_area = defaultdict(list)
        for r, c in chunks:
            by_area[grid.area_of_chunk(r, c)].append((r, c))
        for area, listener in one_each.items():
            assert sorted((r, c) for _t, r, c in listener.got) == sorted(by_area[area]), area
    finally:
        for listener in (plant, every_area, *one_each.values()):
            listener.close()
