"""A pose six days late under load: the embedded service with six days of
history and its snapshots (one every 10 minutes: ~880), twenty robots reporting every
second over MQTT, and in the middle one pose stamped six days ago. Before schema v8 the
sink rebuilt every snapshot since then before committing; that outlasted the consumer's
poll interval and the pipeline stalled for good. Now: every pose is stored, none twice,
the history consumer never failed a commit, the map and robots at the late instant are
exact, and the snapshot timer repairs the snapshots in the background (the first step is waited for).

Bounded: writing the history ~40 s, the stack ~20 s, the load 30 s, each wait <= 90 s.
The latencies are printed, not asserted (benchmarks measure speed; this checks that
nothing stalls)."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import httpx
import pytest

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.core.wire2019 import encode_coordinates, format_timestamp
from mapservice.local.stack import Stack

pytestmark = pytest.mark.long

ROBOTS, SECONDS = 20, 30
DAY_MS = 86_400_000
REPAIR_TICK_S = 2.0


def now_ms() -> int:
    return time.time_ns() // 1_000_000


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    data_dir = tmp_path_factory.mktemp("late") / "data"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "demo-history",
            "--data-dir",
            str(data_dir),
            "--days",
            "6.05",
            "--robots",
            "1",
        ],
        check=True,
        timeout=600,
        capture_output=True,
    )
    # The snapshot timer ticks every REPAIR_TICK_S instead of every 30 s (a quarter of the
    # 10-minute snapshot interval, at most 30 s): its first repair step comes that soon.
    stack = Stack(
        data_dir, mqtt="mosquitto", extra_env={"MAPSERVICE_SNAPSHOT_TICK_S": str(REPAIR_TICK_S)}
    )
    with stack.running():
        yield stack


def publish_load(stack, late: tuple[str, bytes], sent: list) -> None:
    """ROBOTS poses a second for SECONDS, QoS 1; the late pose after a third of it."""
    host, port, _ = parse_mqtt_url(stack.mqtt_url)
    client = make_client(f"late-load-{now_ms()}")
    client.connect(host, port)
    client.loop_start()
    try:
        start = time.monotonic()
        for second in range(SECONDS):
            ts = now_ms()
            infos = [
                client.publish(
                    f"iot/coordinates/load-{r}",
                    encode_coordinates(
                        f"load-{r}",
                        format_timestamp(ts),
                        float(second),
                        float(r),
                        battery_level=50.0,
                    ),
                    qos=1,
                )
                for r in range(ROBOTS)
            ]
            sent.extend((f"load-{r}", ts) for r in range(ROBOTS))
            if second == SECONDS // 3:
                infos.append(client.publish(*late, qos=1))
            for info in infos:
                info.wait_for_publish(30)
            time.sleep(max(0.0, start + second + 1 - time.monotonic()))
    finally:
        client.loop_stop()
        client.disconnect()


def metric(text: str, name: str) -> float:
    found = re.findall(rf"^{name}(?:{{[^}}]*}})? ([0-9.e+-]+)$", text, re.M)
    return sum(float(v) for v in found)


def test_a_pose_six_days_late_under_load_stalls_nothing(stack) -> None:
    """All 600 load poses stored once, no commit failure, the late pose exact at its instant."""
    late_ms = now_ms() - 6 * DAY_MS + 3_600_000  # inside the demo history, six days back
    late = (
        "iot/coordinates/late-1",
        encode_coordinates("late-1", format_timestamp(late_ms), 4.5, 7.25, battery_level=33.0),
    )
    sent: list[tuple[str, int]] = []
    started = now_ms()
    publish_load(stack, late, sent)
    http = httpx.Client(base_url=stack.api_url, timeout=30)
    deadline = time.monotonic() + 90
    while True:
        stored = http.get(
            "/api/v1/poses", params={"from": started - 1000, "to": now_ms() + 1, "limit": 100_000}
        ).json()
        mine = [(p["robotId"], p["ts_ms"]) for p in stored if p["robotId"].startswith("load-")]
        if len(set(mine)) >= len(sent) or time.monotonic() > deadline:
            break
        time.sleep(0.25)
    assert sorted(mine) == sorted(sent), f"{len(set(mine))} of {len(sent)} stored"
    lags = sorted(p["receive_time_ms"] - p["ts_ms"] for p in stored)
    print(f"\n{len(sent)} poses stored; receive lag median {lags[len(lags) // 2]} ms")

    robots = http.get("/api/v1/robots", params={"at": late_ms + 500}).json()["robots"]
    (late_robot,) = [r for r in robots if r["robotId"] == "late-1"]
    assert late_robot["ts_ms"] == late_ms and late_robot["position"][:2] == [4.5, 7.25]

    metrics = http.get("/metrics").text
    assert metric(metrics, "mapservice_sink_commit_failures_total") == 0

    # The timer repairs a day of snapshots per tick (every REPAIR_TICK_S here): wait for the
    # first step, not for all six.
    sql = (
        "SELECT toUnixTimestamp64Milli(min(from_ts)), count() FROM mapservice.snapshot_repairs "
        "FORMAT CSV"
    )
    password = (stack.data_dir / "secrets" / "analyst-password").read_text().strip()

    def pending() -> tuple[int, int]:
        first, count = (
            http.post("/clickhouse/", content=sql.encode(), auth=("analyst", password))
            .text.strip()
            .split(",")
        )
        return int(first), int(count)

    deadline = time.monotonic() + 120
    while (state := pending())[1] and state[0] < late_ms + DAY_MS and time.monotonic() < deadline:
        time.sleep(0.25)
    assert state[1] == 0 or state[0] >= late_ms + DAY_MS, f"no repair step in 2 minutes: {state}"
    robots = http.get("/api/v1/robots", params={"at": late_ms + 500}).json()["robots"]
    assert [r["ts_ms"] for r in robots if r["robotId"] == "late-1"] == [late_ms]
