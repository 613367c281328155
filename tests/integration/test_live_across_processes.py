"""Live mode with the processors and two API replicas in separate processes (Apache
Kafka, Mosquitto): every replica's /api/v1/live gets what the processors stored, and a
restarted replica serves live again, from now.

No ClickHouse server is needed for this: each API process opens a chDB directory of its
own (chDB allows one process per directory), so the APIs here serve no history (replica
1 holds just the map meta, for the UI), only the live stream, which reaches them through
Kafka; the UI's live mode is checked in headless Chromium on replica 1. test_split_topology.py runs the
whole split deployment on one ClickHouse. Bounded: about 30 s of waits at most.
"""

from __future__ import annotations

import json
import signal
import time

import pytest
from websockets.sync.client import connect

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.core.events import make_envelope
from mapservice.core.wire2019 import encode_coordinates, format_timestamp
from mapservice.local import embedded
from mapservice.local.checkout import TEST_UI_ENV
from mapservice.local.stack import Stack
from mapservice.settings import Settings
from tests.fixtures.paths import MAPS
from tests.ui.conftest import DIST, module_browser, page  # noqa: F401  (fixtures)

from .conftest import wait_for_meta
from .test_pipeline import now_ms, publish_all


@pytest.fixture(scope="module")
def browser(module_browser):
    """This module's browser ends with the module (see tests/ui/conftest.playwright_browser)."""
    return module_browser


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    root = tmp_path_factory.mktemp("live-apart")
    meta = meta_for(load_ros_map(MAPS / "depot.yaml"))
    # Replica 1's own history: only the map meta, so that the UI can place robots.
    store = ClickHouseStore.from_settings(Settings(data_dir=root / "api-1"))
    try:
        store.migrate()
        store.append([make_envelope("mapservice", now_ms(), now_ms(), meta)])
    finally:
        store.close()
    stack = Stack(root / "processors", mqtt="mosquitto", extra_env=dict(TEST_UI_ENV))
    stack.second_api_port = embedded.free_port()  # type: ignore[attr-defined]
    stack.root = root  # type: ignore[attr-defined]
    with stack.running(
        stack.start_brokers,
        lambda: stack.publish_meta(meta),
        lambda: stack.start_processors(embedded.free_port()),
        lambda: stack.start_api(env={"MAPSERVICE_DATA_DIR": str(root / "api-1")}),
        lambda: stack.start_api(
            stack.second_api_port, name="api-2", env={"MAPSERVICE_DATA_DIR": str(root / "api-2")}
        ),
        stack.start_gateway,
        lambda: wait_for_meta(stack),
    ):
        yield stack


def live_url(port: int) -> str:
    return f"ws://127.0.0.1:{port}/api/v1/live"


def publish_pose(stack: Stack, robot: str) -> int:
    ts = now_ms()
    publish_all(
        stack,
        [(f"iot/coordinates/{robot}", encode_coordinates(robot, format_timestamp(ts), 1.0, 2.0))],
    )
    return ts


def next_of(ws, robot: str, timeout_s: float = 20) -> dict:
    """The first message for `robot` on the socket; others (earlier robots) are passed over."""
    deadline = time.monotonic() + timeout_s
    while True:
        message = json.loads(ws.recv(timeout=max(0.1, deadline - time.monotonic())))
        if message["robotId"] == robot:
            return message


def test_every_api_replica_streams_what_the_processors_stored(stack) -> None:
    """A pose published over MQTT reaches /api/v1/live of both API processes, once each."""
    with (
        connect(live_url(stack.api_port), open_timeout=10) as one,
        connect(live_url(stack.second_api_port), open_timeout=10) as two,
    ):
        ts = publish_pose(stack, "apart-1")
        for ws in (one, two):
            message = next_of(ws, "apart-1")
            assert message["type"] == "pose" and message["ts_ms"] == ts
            assert message["position"][:2] == [1.0, 2.0]


def test_a_restarted_replica_streams_again_from_now(stack) -> None:
    """After a restart an API replica streams new poses and does not replay the old ones."""
    publish_pose(stack, "apart-before")
    with connect(live_url(stack.api_port), open_timeout=10) as one:
        publish_pose(stack, "apart-marker")
        next_of(one, "apart-marker")  # the processors stored everything before it
    proc = stack.procs.pop("api-2")
    proc.send_signal(signal.SIGTERM)
    # uvicorn shuts down gracefully, then re-raises the signal it caught: exit by SIGTERM.
    assert proc.wait(30) in (0, -signal.SIGTERM)
    stack.start_api(
        stack.second_api_port, name="api-2", env={"MAPSERVICE_DATA_DIR": str(stack.root / "api-2")}
    )
    with connect(live_url(stack.second_api_port), open_timeout=10) as two:
        ts = publish_pose(stack, "apart-after")
        got = [json.loads(two.recv(timeout=20))]
        while got[-1].get("robotId") != "apart-after":
            got.append(json.loads(two.recv(timeout=20)))
    assert got[-1]["ts_ms"] == ts
    # Nothing from before the restart: neither the marker nor the pose before it. (What the
    # processors find meanwhile, such as the earlier robots falling silent, comes as it
    # is found: incidents name their robots in a list and are no replay.)
    poses = [m for m in got if m["type"] == "pose"]
    assert [m["robotId"] for m in poses] == ["apart-after"], got


def test_the_ui_live_mode_shows_a_pose_stored_by_another_process(stack, page) -> None:
    """In the browser, live mode on an API replica draws a pose the processors stored elsewhere."""
    page.goto(f"{stack.api_url}/?live=1")
    page.wait_for_function(
        "() => window.__replay && window.__replay.liveStatus.connected", timeout=60_000
    )
    meta = page.evaluate("() => window.__replay.meta")
    x, y = meta["origin"][0] + 10.0, meta["origin"][1] + 10.0
    ts = now_ms()
    publish_all(
        stack,
        [("iot/coordinates/apart-ui", encode_coordinates("apart-ui", format_timestamp(ts), x, y))],
    )
    page.wait_for_function(
        "() => window.__replay.drawnRobots().some(r => r.robotId === 'apart-ui')", timeout=30_000
    )
    shown = {r["robotId"]: r for r in page.evaluate("() => window.__replay.robots()")}
    assert shown["apart-ui"]["x"] == pytest.approx(x) and shown["apart-ui"]["y"] == pytest.approx(y)
    assert page.evaluate("() => window.__replay.liveStatus.reconnects") == 0
    assert not page.errors
