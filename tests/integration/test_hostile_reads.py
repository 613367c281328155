"""Readers and analysts never starve the probes or the ingest: the real stack as `mapservice
up` runs it (the ClickHouse server over the embedded chDB, the processors and the API each
a process of its own; Kafka as the stacks embed it, Mosquitto) over hours of history, a
robot fleet publishing, in three phases:

- alone (the baseline);
- with 20 anonymous readers (each from its own address) on the costliest reads there
  are: 24 h MCAP exports, 7-day CSV exports, large pose and event windows and map PNGs,
  asked again as soon as answered (or refused);
- with 60 concurrent analysts' `SELECT sleep(3)` on /clickhouse, each asked again as soon
  as answered (or refused).

Asserted in each phase: the probes answer within a second, publish-to-queryable (publish
to the live stream's copy, which is sent once the event is stored) has a p99 of at most
2 s, the history consumer never left its group (no second partition assignment in the
processors' log), and the service's resident memory (the sum over its three processes,
sampled together) stays under MEMORY_BOUND. The time bounds are judged only where the
machine's load average is at most OVERLOADED per core (a shared machine at 15 per core
missed them with no reader at all); beyond, a miss skips the test with the figures, the
other bounds still asserted. A phase that misses a time bound runs once more and is judged
by that second run (the first one's figures kept beside it): one stall of the pipeline of
a few seconds, whatever its cause, misses the p99 of a PHASE_S phase (the robots publish
through all of it, so it delays far more than 1 % of the poses), but a load that starves
probes or ingest misses it twice. The crowd's clients run before the fleet starts and until
its last poses arrived: the hostile load covers each phase's every probe and pose. The figures of all phases are printed (run with -s) and
written to test-artifacts/hostile-reads.json for BENCHMARKS.md. Bounded:
three phases of PHASE_S plus the history's load, about a minute on an idle machine.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import threading
import time

import httpx
import pytest
from websockets.sync.client import connect

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import load_ros_map
from mapservice.bench.history_loader import load_history
from mapservice.local.stack import Stack
from mapservice.robot.loadgen import RobotFleet
from mapservice.sql.credentials import analyst_password
from tests.fixtures.paths import MAPS, ROOT

from .conftest import wait_for_meta

pytestmark = pytest.mark.alone

HISTORY_HOURS = 6
HISTORY_ROBOTS = 20
FLEET = 100  # robots publishing a pose a second (and a chunk every five)
PHASE_S = 10  # 1,000 poses a phase: its p99 is its 10 slowest
READERS = 20
ANALYSTS = 60
# The service's RSS: the ClickHouse server (chDB), the processors and the API together.
MEMORY_BOUND = 3 * 1024**3
SERVICE = ("clickhouse", "processors", "api")
ASSIGNED = "history partitions assigned"
ARTIFACT = ROOT / "test-artifacts" / "hostile-reads.json"
OVERLOADED = 4  # load average per core beyond which the time bounds are not judged
LAST_POSES_S = 5.0  # longest wait for the last poses of a phase to arrive live


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = Stack(tmp_path_factory.mktemp("hostile"), mqtt="mosquitto", apart=True)
    settings = stack.settings()
    ros_map = load_ros_map(MAPS / "warehouse.yaml")
    store = ClickHouseStore(
        settings.resolved_clickhouse_dsn, settings.clickhouse_database, settings.retention_days
    )
    try:
        result = load_history(
            store,
            ros_map,
            days=HISTORY_HOURS / 24,
            robots=HISTORY_ROBOTS,
            end_ms=time.time_ns() // 1_000_000 - 120_000,
        )
    finally:
        store.close()
    stack.start(
        stack.start_brokers,
        lambda: stack.publish_meta(result.meta),
        stack.start_apart,
        stack.start_gateway,
        lambda: wait_for_meta(stack),
    )
    stack.ros_map = ros_map  # type: ignore[attr-defined]
    yield stack
    stack.stop()


class Probes(threading.Thread):
    """/healthz and /readyz four times a second; the slowest answer and any failure."""

    def __init__(self, api: str) -> None:
        super().__init__(daemon=True)
        self.api, self.stop = api, threading.Event()
        self.slowest, self.failures = 0.0, []

    def run(self) -> None:
        with httpx.Client(base_url=self.api, timeout=10) as client:
            while not self.stop.is_set():
                for path in ("/healthz", "/readyz"):
                    started = time.monotonic()
                    try:
                        status = client.get(path).status_code
                    except httpx.HTTPError as exc:
                        status = repr(exc)
                    self.slowest = max(self.slowest, time.monotonic() - started)
                    if status != 200:
                        self.failures.append((path, status))
                self.stop.wait(0.25)


def rss(pid: int) -> int:
    status = open(f"/proc/{pid}/status").read()
    return int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) * 1024


class Memory(threading.Thread):
    """The largest resident size of the processes together (sampled at once every half
    second), and each one's own largest."""

    def __init__(self, pids: dict[str, int]) -> None:
        super().__init__(daemon=True)
        self.pids, self.stop, self.peak = pids, threading.Event(), 0
        self.peaks = dict.fromkeys(pids, 0)

    def run(self) -> None:
        while not self.stop.is_set():
            now = {name: rss(pid) for name, pid in self.pids.items()}
            self.peak = max(self.peak, sum(now.values()))
            self.peaks = {name: max(self.peaks[name], now[name]) for name in now}
            self.stop.wait(0.5)


class Live(threading.Thread):
    """The live stream: when each of the fleet's poses arrived (its copy is sent once the
    event is queryable)."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.url, self.stop, self.arrived = url, threading.Event(), {}
        self.connected = threading.Event()

    def run(self) -> None:
        with connect(self.url + "/api/v1/live?batch=true", max_size=None) as ws:
            self.connected.set()
            while not self.stop.is_set():
                try:
                    frame = ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                now = time.time()
                for event in json.loads(frame):
                    if event.get("type") == "pose":
                        self.arrived.setdefault((event["robotId"], event["ts_ms"]), now)


def readers(api: str, stop: threading.Event, tally: dict) -> list[threading.Thread]:
    """READERS anonymous clients, each from its own loopback address, on costly reads."""
    now = time.time_ns() // 1_000_000
    paths = [
        f"/api/v1/exports/replay.mcap?from={now - 86_400_000}&to={now}",
        f"/api/v1/exports/tables/robot-poses?from={now - 7 * 86_400_000 + 120_000}&to={now}",
        f"/api/v1/poses?from={now - 86_400_000}&to={now}&limit=100000",
        f"/api/v1/events?from={now - 6 * 3_600_000}&to={now}",
        f"/api/v1/map/png?at={now - 3_600_000}&scale=4",
    ]
    lock = threading.Lock()

    def read(n: int) -> None:
        transport = httpx.HTTPTransport(local_address=f"127.0.0.{n + 10}")
        with httpx.Client(base_url=api, transport=transport, timeout=120) as client:
            k = n
            while not stop.is_set():
                path = paths[k % len(paths)]
                k += 1
                try:
                    with client.stream("GET", path) as reply:
                        for _ in reply.iter_bytes():
                            if stop.is_set():
                                break
                        status = reply.status_code
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                with lock:
                    tally[status] = tally.get(status, 0) + 1
                if status != 200:
                    stop.wait(0.1)  # hostile, not a busy loop: the refusal is cheap either way

    return [threading.Thread(target=read, args=(n,), daemon=True) for n in range(READERS)]


def analysts(api: str, password: str, stop: threading.Event, tally: dict) -> list[threading.Thread]:
    """ANALYSTS clients with the analyst's credential, each on `SELECT sleep(3)` (almost no
    CPU; it holds whatever runs it for 3 s), asked again as soon as answered (or refused)."""
    lock = threading.Lock()

    def query() -> None:
        with httpx.Client(base_url=api, timeout=60, auth=("analyst", password)) as client:
            while not stop.is_set():
                try:
                    status = client.post("/clickhouse/", content=b"SELECT sleep(3)").status_code
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                with lock:
                    tally[status] = tally.get(status, 0) + 1
                if status != 200:
                    stop.wait(0.25)

    return [threading.Thread(target=query, daemon=True) for _ in range(ANALYSTS)]


def crowd(load: str, api: str, password: str, seconds: float, out, started, done) -> None:
    """A process of its own for the readers or the analysts, so that the measuring threads
    (probes, live stream, fleet) never wait for this process's GIL behind them: what is
    measured is the service's delay, not the load generator's. Sets `started` once its
    clients run, stops when `done` is set (at most `seconds`), then puts its tally on `out`."""
    stop, tally = threading.Event(), {}
    clients = (
        readers(api, stop, tally) if load == "readers" else analysts(api, password, stop, tally)
    )
    for t in clients:
        t.start()
    started.set()
    done.wait(seconds)
    stop.set()
    for t in clients:
        t.join(30)
    out.put({str(k): v for k, v in tally.items()})


def wait_seen_live(live: Live, published: list, timeout_s: float) -> None:
    """Until every published pose arrived on the live stream, at most `timeout_s` (the
    figures then count what did not)."""
    poses = [(robot, ts) for kind, robot, ts, _ in published if kind == "pose"]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not all(p in live.arrived for p in poses):
        time.sleep(0.1)


def run_phase(stack: Stack, load: str) -> dict:
    processors_log = stack.log_dir / "processors.log"
    assignments_before = processors_log.read_text().count(ASSIGNED)
    probes, live = Probes(stack.api_url), Live(stack.api_url.replace("http://", "ws://"))
    memory = Memory({name: stack.procs[name].pid for name in SERVICE})
    for t in (probes, memory, live):
        t.start()
    assert live.connected.wait(30), "the live stream did not connect"
    context = multiprocessing.get_context("spawn")
    tallies, started, done = context.Queue(), context.Event(), context.Event()
    clients = (
        []
        if load == "baseline"
        else [
            context.Process(
                target=crowd,
                args=(
                    load,
                    stack.api_url,
                    analyst_password(stack.settings()),
                    PHASE_S + 60.0,
                    tallies,
                    started,
                    done,
                ),
                daemon=True,
            )
        ]
    )
    for process in clients:
        process.start()
    # The whole phase under the load: the fleet starts once the crowd's clients run.
    assert not clients or started.wait(60), f"the {load} did not start"
    fleet = RobotFleet(stack.mqtt_url, stack.ros_map, FLEET, prefix=load, record=True)
    stats = fleet.run(PHASE_S)
    wait_seen_live(live, stats.published, LAST_POSES_S)  # the last poses' way through
    done.set()
    tally = tallies.get(timeout=90) if clients else {}
    for t in (probes, memory, live):
        t.stop.set()
    for t in (*clients, probes, memory, live):
        t.join(30)
    latencies = sorted(
        live.arrived[(robot, ts)] - at
        for kind, robot, ts, at in stats.published
        if kind == "pose" and (robot, ts) in live.arrived
    )
    poses = sum(1 for kind, *_ in stats.published if kind == "pose")
    figures = {
        "load": load,
        "clients": {"baseline": 0, "readers": READERS, "analysts": ANALYSTS}[load],
        "fleet": FLEET,
        "seconds": PHASE_S,
        "poses_published": poses,
        "poses_seen_live": len(latencies),
        "publish_to_queryable_p50_s": round(latencies[len(latencies) // 2], 3)
        if latencies
        else None,
        "publish_to_queryable_p99_s": round(latencies[int(len(latencies) * 0.99)], 3)
        if latencies
        else None,
        "slowest_probe_s": round(probes.slowest, 3),
        "probe_failures": probes.failures[:5],
        "service_peak_rss_mb": memory.peak // 2**20,
        "peak_rss_mb": {name: peak // 2**20 for name, peak in memory.peaks.items()},
        "consumer_assignments": processors_log.read_text().count(ASSIGNED) - assignments_before,
        "answers": tally,
        # The machine's, at the phase's end: on a shared machine it says what else ran.
        "load_average_1m": round(os.getloadavg()[0], 1),
    }
    print(f"\nhostile-read figures: {json.dumps(figures)}")
    return figures


def on_time(figures: dict) -> bool:
    p99 = figures["publish_to_queryable_p99_s"]
    return figures["slowest_probe_s"] < 1.0 and p99 is not None and p99 <= 2.0


def test_readers_and_analysts_do_not_starve_probes_or_ingest(stack) -> None:
    # `up`'s topology: the history consumer's process serves no HTTP but its health port.
    assert "server" not in stack.procs and len({stack.procs[n].pid for n in SERVICE}) == 3
    # The consumer's assignment is logged (kafka_batch_source.py): once at start, again
    # whenever it left its group and rejoined; a log without it would prove nothing.
    assert (stack.log_dir / "processors.log").read_text().count(ASSIGNED) == 1
    phases = {}
    for load in ("baseline", "readers", "analysts"):
        figures = run_phase(stack, load)
        if not on_time(figures):
            # One stall of the pipeline (a merge, a snapshot) of 2.5 s puts a phase's p99
            # past 2 s; a load that starves probes or ingest misses the bounds again.
            figures = {**run_phase(stack, load), "late_first_run": figures}
        phases[load] = figures
    ARTIFACT.parent.mkdir(parents=True, exist_ok=True)
    ARTIFACT.write_text(
        json.dumps({"memory_bound_mb": MEMORY_BOUND // 2**20, **phases}, indent=2) + "\n"
    )
    for figures in phases.values():
        for run in (figures, figures.get("late_first_run", figures)):
            assert run["poses_seen_live"] >= 0.99 * run["poses_published"], figures
            assert not run["probe_failures"], figures
            assert run["consumer_assignments"] == 0, figures  # never left its group
            assert run["service_peak_rss_mb"] * 2**20 < MEMORY_BOUND, figures
    late = [figures for figures in phases.values() if not on_time(figures)]
    # The readers did read and the analysts' sleeps ran (beyond the analysts' gate they
    # were refused with "too many queries"), not just failed.
    assert phases["readers"]["answers"].get("200", 0) > 0, phases["readers"]
    assert phases["analysts"]["answers"].get("200", 0) > 0, phases["analysts"]
    assert phases["analysts"]["answers"].get("503", 0) > 0, phases["analysts"]
    # The time bounds (probes within 1 s, p99 at most 2 s) are judged where the machine
    # gives the service its cores: on one with a load average over OVERLOADED per core
    # (other work; the baseline's figures show it too) a miss is reported, not judged.
    overloaded = [f for f in late if f["load_average_1m"] > OVERLOADED * (os.cpu_count() or 1)]
    if overloaded and len(overloaded) == len(late):
        pytest.skip(
            "time bounds not judged: the machine's load average was "
            + ", ".join(f"{f['load_average_1m']} ({f['load']})" for f in late)
            + f" on {os.cpu_count()} cores: "
            + json.dumps(late)
        )
    assert not late, late
