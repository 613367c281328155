"""The split deployment, as compose and Kubernetes run it: gateway, processors and two API
replicas as separate `mapservice <component>` processes, against Apache Kafka, Mosquitto and one
ClickHouse reached over its HTTP interface (`mapservice clickhouse-server`: chDB behind
the ClickHouse HTTP protocol, the one process that opens the data directory).

Checks, on that topology: the whole 2019 contract suite (the same test functions the
embedded-mode stack runs, imported from test_contract_2019), a replay seek through the API
and in the browser (map and robots at T are what was published), and live mode: a pose
published over MQTT reaches both API replicas' /api/v1/live and the UI's live map in
headless Chromium.

What this does not cover compared with a real ClickHouse server: the server here is chDB
(the same ClickHouse engine and SQL) behind a small HTTP front end, so ClickHouse's own
server-side parts are not exercised: users, quotas and settings profiles, the native TCP
protocol, concurrent-session limits, and asynchronous inserts. Kafka is the embedded Apache Kafka:
one node, so no replication. Bounded: each wait is seconds to a minute; the module
takes about a minute on an idle machine.
"""

from __future__ import annotations

import base64
import io
import json
import subprocess
import sys
import time
import zlib

import httpx
import msgspec
import pytest
from mcap.reader import make_reader
from websockets.sync.client import connect

from mapservice.core.wire2019 import content_hash, format_timestamp
from mapservice.local import embedded
from mapservice.local.checkout import TEST_UI_ENV
from mapservice.local.stack import Stack
from tests.ui.conftest import DIST, module_browser, page  # noqa: F401  (fixtures)

from . import test_contract_2019 as contract
from .conftest import merge_threads_lowered
from .test_contract_2019 import TOKEN, http, robot, until  # noqa: F401  (http, robot: fixtures)
from .test_pipeline import now_ms, pose_rounds, publish_all


@pytest.fixture(scope="module")
def browser(module_browser):
    """This module's browser ends with the module (see tests/ui/conftest.playwright_browser)."""
    return module_browser


TIMEOUT_MS = 60_000


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """Brokers, the ClickHouse HTTP server, processors, two API replicas and the gateway,
    each its own process; no map meta published (the 2019 start-up sequence runs first)."""
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    stack = Stack(
        tmp_path_factory.mktemp("stack-split"),
        mqtt="mosquitto",
        apart=True,
        extra_env={**TEST_UI_ENV, "MAPSERVICE_ADMIN_TOKEN": TOKEN},
    )
    stack.extra_env["MAPSERVICE_PUBLIC_BASE_URL"] = stack.api_url
    stack.second_api_url = f"http://127.0.0.1:{embedded.free_port()}"  # type: ignore[attr-defined]
    with stack.running(
        stack.start_brokers,
        stack.start_apart,
        lambda: stack.start_api(int(stack.second_api_url.rsplit(":", 1)[1]), name="api-2"),
        stack.start_gateway,
    ):
        yield stack


# The 2019 contract suite, the same functions as in the embedded mode, in its file order
# (each builds on the data of the ones before).
test_robot_start_up_sequence = contract.test_robot_start_up_sequence
test_listings_10_11_13_post_a_chunk_and_read_it_back = (
    contract.test_listings_10_11_13_post_a_chunk_and_read_it_back
)
test_post_chunk_is_validated_like_mqtt = contract.test_post_chunk_is_validated_like_mqtt
test_writes_need_the_robot_token_and_json = contract.test_writes_need_the_robot_token_and_json
test_listing_12_query_parameters = contract.test_listing_12_query_parameters
test_bad_and_unknown_parameters = contract.test_bad_and_unknown_parameters
test_listings_16_17_coordinates = contract.test_listings_16_17_coordinates


def test_each_component_is_its_own_process_on_one_clickhouse_server(stack) -> None:
    """Gateway, processors and both APIs run apart; the APIs read the server, not chDB files."""
    assert {"gateway", "processors", "api", "api-2", "clickhouse"} <= set(stack.procs)
    assert "server" not in stack.procs  # no `mapservice serve`: nothing shares a process
    # The server serves the data dir's chDB (not a directory named after its own URL).
    assert (stack.data_dir / "clickhouse" / "metadata" / "mapservice").exists()
    assert all(p.poll() is None for p in stack.procs.values())
    for url in (stack.api_url, stack.second_api_url):
        assert httpx.get(f"{url}/readyz", timeout=10).json()["ok"] is True


def pixels_b64(shade: int) -> tuple[str, str]:
    pixels = bytes([shade]) * 10_000
    return base64.b64encode(zlib.compress(pixels)).decode(), content_hash(pixels).hex()


def test_a_replay_seek_shows_what_was_published_at_t(stack, http, page) -> None:
    """Map and robots at T, through the API and in the UI, are the writes published up to T."""
    t0 = (now_ms() // 1000 - 30) * 1000
    (a, hash_a), (b, hash_b) = pixels_b64(11), pixels_b64(222)

    def chunk(data, ts, robot):
        return (
            "iot/chunks/create",
            json.dumps(
                {
                    "pgmB64compressedData": data,
                    "row": 0,
                    "column": 0,
                    "timestamp": format_timestamp(ts),
                    "robotId": robot,
                }
            ).encode(),
        )

    def pose(robot, ts, x):
        return (
            f"iot/coordinates/{robot}",
            json.dumps(
                {
                    "robotId": robot,
                    "timestamp": format_timestamp(ts),
                    "pose": {
                        "position": {"x": x, "y": 3.0, "z": 0},
                        "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
                    },
                    "status": {
                        "battery": {"battery_level": 50, "charging": False},
                        "loaded": False,
                    },
                }
            ).encode(),
        )

    publish_all(
        stack,
        [
            chunk(a, t0, "split-a"),
            chunk(b, t0 + 2000, "split-b"),
            pose("split-a", t0, 1.0),
            pose("split-a", t0 + 1000, 2.0),
            pose("split-b", t0 + 2000, 5.0),
        ],
    )

    def at(t: int) -> tuple[dict, dict]:
        m = http.get("/api/v1/map", params={"at": t}).json()
        r = http.get("/api/v1/robots", params={"at": t}).json()
        return (
            {(c["row"], c["column"]): (c["robotId"], c["content_hash"]) for c in m["chunks"]},
            {
                p["robotId"]: (p["ts_ms"], p["position"][0])
                for p in r["robots"]
                if p["robotId"].startswith("split-")
            },
        )

    until(
        lambda: at(t0 + 2000),
        lambda got: got[0].get((0, 0)) == ("split-b", hash_b) and "split-b" in got[1],
        what="the published writes stored",
    )
    chunks, robots = at(t0 + 1000)
    assert chunks[(0, 0)] == ("split-a", hash_a)
    assert robots == {"split-a": (t0 + 1000, 2.0)}
    assert at(t0 + 2000)[1] == {"split-a": (t0 + 1000, 2.0), "split-b": (t0 + 2000, 5.0)}

    page.goto(f"{stack.api_url}/?t={t0 + 1000}")
    page.wait_for_function("() => window.__replay && window.__replay.complete", timeout=TIMEOUT_MS)
    assert page.evaluate("() => window.__replay.playhead") == t0 + 1000
    shown = page.evaluate(
        "() => Object.fromEntries([...window.__replay.engine.state.cells.values()]"
        ".map(c => [`${c.row}:${c.column}`, c.content_hash]))"
    )
    assert shown["0:0"] == hash_a
    shown_robots = {
        r["robotId"]: (r["ts_ms"], r["x"])
        for r in page.evaluate("() => window.__replay.robots()")
        if r["robotId"].startswith("split-")
    }
    assert shown_robots == {"split-a": (t0 + 1000, 2.0)}
    assert not page.errors


def test_live_mode_reaches_every_api_replica_and_the_browser(stack, page) -> None:
    """A pose published over MQTT arrives on both replicas' /api/v1/live and on the UI's live map."""
    page.goto(f"{stack.api_url}/?live=1")
    page.wait_for_function(
        "() => window.__replay && window.__replay.liveStatus.connected", timeout=TIMEOUT_MS
    )
    sockets = [
        connect(url.replace("http://", "ws://") + "/api/v1/live", open_timeout=10)
        for url in (stack.api_url, stack.second_api_url)
    ]
    try:
        time.sleep(0.5)
        meta = page.evaluate("() => window.__replay.meta")
        x, y = meta["origin"][0] + 10.0, meta["origin"][1] + 10.0
        ts = now_ms() // 1000 * 1000
        publish_all(
            stack,
            [
                (
                    "iot/coordinates/split-live",
                    json.dumps(
                        {
                            "robotId": "split-live",
                            "timestamp": format_timestamp(ts),
                            "pose": {
                                "position": {"x": x, "y": y, "z": 0},
                                "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
                            },
                            "status": {
                                "battery": {"battery_level": 80, "charging": False},
                                "loaded": True,
                            },
                        }
                    ).encode(),
                )
            ],
        )
        for ws in sockets:
            deadline = time.monotonic() + 30
            message: dict = {}
            while time.monotonic() < deadline and message.get("robotId") != "split-live":
                message = json.loads(ws.recv(timeout=30))
            assert message["robotId"] == "split-live" and message["ts_ms"] == ts
            assert (
                message["position"][:2] == [x, y]
                and message["sent_ms"] >= message["receive_time_ms"]
            )
    finally:
        for ws in sockets:
            ws.close()
    page.wait_for_function(
        "() => window.__replay.drawnRobots().some(r => r.robotId === 'split-live')",
        timeout=TIMEOUT_MS,
    )
    shown = {r["robotId"]: r for r in page.evaluate("() => window.__replay.robots()")}
    assert shown["split-live"]["x"] == pytest.approx(x) and shown["split-live"][
        "y"
    ] == pytest.approx(y)
    assert page.evaluate("() => window.__replay.liveStatus.reconnects") == 0
    assert not page.errors


def test_a_batch_of_2000_chunk_contents_through_the_clickhouse_server(stack, http) -> None:
    """The UI's largest batch: the store's IN list of 2,000 hashes goes to the server as
    multipart parameters (clickhouse-connect, over 4 KB), which the server reads."""
    seen = http.get("/api/v1/map").json()["chunks"]
    known = sorted({c["content_hash"] for c in seen})
    assert known, "no chunk stored yet"
    hashes = known + [f"{n:032x}" for n in range(2000 - len(known))]
    reply = http.post("/api/v1/chunk-contents/batch", json={"hashes": hashes})
    assert reply.status_code == 200, reply.text[:500]
    answer = msgspec.msgpack.decode(reply.content)
    assert sorted(c[0] for c in answer["contents"]) == known
    assert len(answer["missing"]) == 2000 - len(known)


def test_the_clickhouse_server_runs_its_merges_at_a_lower_cpu_priority(stack) -> None:
    """`mapservice clickhouse-server` holds the chDB directory, so its merges run there: at
    MAPSERVICE_CHDB_MERGE_NICE (19 by default), and no other of its threads."""
    merge_threads_lowered(stack.procs["clickhouse"].pid, pose_rounds(stack))


def test_export_replay_through_the_clickhouse_server(stack, tmp_path) -> None:
    """`mapservice export replay` of the last ten minutes: an MCAP with the map and the
    robots the replay test published, after 150 chunk writes of distinct contents (the
    export asks for their contents at once: over clickhouse-connect's 4 KB threshold)."""
    t0 = (now_ms() // 1000 - 20) * 1000
    writes = []
    for n in range(150):
        pixels = bytes([n]) * 9_999 + bytes([n // 2])
        writes.append(
            (
                "iot/chunks/create",
                json.dumps(
                    {
                        "pgmB64compressedData": base64.b64encode(zlib.compress(pixels)).decode(),
                        "row": 0,
                        "column": 0,
                        "timestamp": format_timestamp(t0 + 10 * n),
                        "robotId": "split-many",
                    }
                ).encode(),
            )
        )
    publish_all(stack, writes)
    last = content_hash(bytes([149]) * 9_999 + bytes([74])).hex()
    until(
        lambda: httpx.get(
            f"{stack.api_url}/api/v1/map", params={"at": t0 + 1490}, timeout=30
        ).json(),
        lambda m: any(c["content_hash"] == last for c in m["chunks"]),
        what="150 writes stored",
    )
    now = now_ms()
    out = tmp_path / "split.mcap"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "export",
            "replay",
            "--from",
            str(now - 600_000),
            "--to",
            str(now),
            "--api",
            stack.api_url,
            "--out",
            str(out),
        ],
        env=stack.env(),
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    summary = make_reader(io.BytesIO(out.read_bytes())).get_summary()
    topics = {summary.channels[c].topic for c in summary.statistics.channel_message_counts}
    assert "/map" in topics and {"/robots/split-a/pose", "/robots/split-b/pose"} <= topics


def test_no_analyst_reads_a_secret_through_either_front_end(stack) -> None:
    """The attack suite on the API replica's /clickhouse (forwarded to the server) and on
    the ClickHouse server's own analyst user: each refused with 497, no secret in a reply."""
    from mapservice.sql.credentials import analyst_password_file
    from tests.mapservice.sql.attacks import ATTACKS

    password = analyst_password_file(stack.data_dir).read_text().strip()
    secret = stack.data_dir / "secrets" / "analyst-password"
    ch_url = stack.clickhouse_url
    for url in (f"{stack.second_api_url}/clickhouse/", ch_url + "/"):
        for name, template in ATTACKS:
            sql = template.format(data=stack.data_dir, secret=secret)
            reply = httpx.post(url, content=sql.encode(), auth=("analyst", password), timeout=30)
            assert reply.status_code == 403, (url, name, reply.text)
            assert reply.headers["X-ClickHouse-Exception-Code"] == "497", (url, name, reply.text)
            assert password not in reply.text


# Last, as in the embedded suite: it wipes the data.
test_deletes_need_the_admin_token = contract.test_deletes_need_the_admin_token


def test_an_api_replica_serves_analysts_read_only_from_the_server(stack) -> None:
    """The API's /clickhouse forwards to the ClickHouse server with readonly=1: reads work,
    writes are refused by the server, a wrong password by the API."""
    import clickhouse_connect

    from mapservice.sql.credentials import analyst_password_file

    password = analyst_password_file(stack.data_dir).read_text().strip()
    port = int(stack.second_api_url.rsplit(":", 1)[1])
    client = clickhouse_connect.get_client(
        host="127.0.0.1", port=port, username="analyst", password=password, proxy_path="/clickhouse"
    )
    assert client.query("SELECT count() FROM mapservice.robot_poses").result_rows[0][0] > 0
    with pytest.raises(Exception, match="164"):
        client.command("TRUNCATE TABLE mapservice.poses")
    reply = httpx.post(
        f"{stack.second_api_url}/clickhouse/", content=b"SELECT 1", auth=("analyst", "x")
    )
    assert reply.status_code == 403


def test_an_api_replica_exports_only_its_own_metrics(stack) -> None:
    """`mapservice api` alone: API request metrics, none of the processors' counters."""
    assert httpx.get(f"{stack.second_api_url}/api/v1/stats", timeout=10).status_code == 200
    text = httpx.get(f"{stack.second_api_url}/metrics", timeout=10).text
    assert "mapservice_api_requests_total" in text
    for processors_metric in (
        "mapservice_sink_events_total",
        "mapservice_snapshot_runs_total",
        "mapservice_sink_insert_failures_total",
    ):
        assert processors_metric not in text, processors_metric
