"""`mapservice bench foxglove`: the Foxglove WebSocket server measured from outside with
Foxglove's own npm client (@foxglove/ws-protocol in node: tests/foxglove_client/bench.mjs,
foxglove_clients.py), in two phases.

- live fan-out: the stack as `mapservice up` runs it (Kafka, the MQTT broker, the ClickHouse
  server, the processors, the API and the gateway each a process; the map uploaded), the
  ingest bench's load fleet (`RawFleet`: `--robots` robots, a pose a second and a chunk
  every five seconds, over MQTT) and `--clients` clients on the live address, each
  subscribed to every channel. Over `--seconds` with the clients connected: the API
  process's CPU (it is the Foxglove server; in `up` it serves the HTTP API too, idle here)
  over the messages all clients received, the messages a second each client got, each
  pose's delivery latency (the robot's publish, whose timestamp is the wall clock then, to
  the client's receipt, on one clock) and the share of published poses each client got.
  `--baseline-seconds` first with no client: what the API process spends on the live
  stream anyway, so the marginal CPU per message is stated too.
- seek to first frame: `--days` of `--seek-robots` robots loaded by the bulk loader (as
  `bench ui` loads them; `--data-dir` keeps and reuses it, the load is timed), served by
  `mapservice api`; one client on the replay address (the playback-control capability)
  seeks, paused, to `--seeks` random instants of the history within the replay window.
  From the request, the time to the first complete frame: the floor logged at T and a pose
  of every robot `/api/v1/robots?at=T` lists (asked after the seek's messages, so the API
  warms nothing the seek reads). The first seek (the session's cold caches) is reported apart.

Progress goes to the terminal and to DATA_DIR/bench-foxglove.log; the results as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import psutil

from mapservice.bench.foxglove_clients import NodeClients
from mapservice.bench.procstat import cpu_seconds
from mapservice.bench.ui_browser import percentile
from mapservice.bench.workdir import DATA_DIR_HELP, bench_data_dir

if TYPE_CHECKING:
    from mapservice.local.stack import Stack

SETTLE_S = 5.0  # the fleet's pipeline, then the clients' subscriptions, at their pace
CONNECT_TIMEOUT_S = 120.0
SEEK_TIMEOUT_S = 120.0
SEEK_GAP_S = 0.5  # between seeks: the previous seek's last reads are done
# Poses published this long before the measurement's end count in the delivered share (each
# has had the time to reach every client; later ones may still be on their way).
DELIVERY_GRACE_MS = 3000
POSE_PREFIX = "robot-"  # the load fleet's robot ids (robot/loadgen.py fleet_robot_id)


class Progress:
    """A line to the terminal (stderr) and to the run's log file."""

    def __init__(self, log_path: Path) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self.log_path = log_path

    def __call__(self, line: str) -> None:
        stamped = f"{time.strftime('%H:%M:%S')} bench foxglove: {line}"
        print(stamped, file=sys.stderr, flush=True)
        with open(self.log_path, "a") as log:
            log.write(stamped + "\n")


def main(args: argparse.Namespace) -> None:
    from mapservice.bench.machine import machine_facts

    if min(args.robots, args.clients, args.seconds) <= 0 or args.seeks < 0:
        raise SystemExit("--robots, --clients and --seconds must be positive, --seeks not negative")
    with bench_data_dir(args.data_dir, "bench-foxglove-") as base:
        say = Progress(base / "bench-foxglove.log")
        out: dict[str, Any] = {
            "benchmark": "foxglove",
            "command": "mapservice " + " ".join(sys.argv[1:]),
            "machine": machine_facts(),
            "client": "@foxglove/ws-protocol (npm) in node, tests/foxglove_client/bench.mjs",
            "data_dir": str(base),
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "loadavg_before": os.getloadavg(),
        }
        if args.live:
            out["live"] = live_phase(args, base, say)
            say("live: " + json.dumps(summary({"live": out["live"]})))
        if args.seeks:
            out["seek"] = seek_phase(args, base, say)
        out["loadavg_after"] = os.getloadavg()
        out["ended_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        out["summary"] = summary(out)
        say("summary: " + json.dumps(out["summary"]))
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


def summary(out: dict[str, Any]) -> dict[str, Any]:
    """The figures BENCHMARKS.md quotes."""
    doc: dict[str, Any] = {}
    live = out.get("live")
    if live:
        for key in (
            "api_cpu_us_per_message",
            "marginal_cpu_us_per_message",
            "messages_per_s_per_client_median",
            "pose_latency_p50_ms",
            "pose_latency_p95_ms",
            "poses_received_fraction_min",
            "clients_closed",
        ):
            doc[key] = live.get(key)
    seek = out.get("seek")
    if seek:
        for key in ("load_s", "reused", "frame_p50_ms", "frame_p95_ms", "incomplete"):
            doc[f"seek_{key}"] = seek.get(key)
    return doc


# --- live fan-out -------------------------------------------------------------------------


def live_phase(args: argparse.Namespace, base: Path, say: Progress) -> dict[str, Any]:
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.bench.fleet.rawfleet import RawFleet
    from mapservice.bench.ingest.cpu import CpuMeter
    from mapservice.bench.ingest.run import LOADGEN_NICE, warm_up
    from mapservice.bench.yardstick import yardstick_ms
    from mapservice.local.stack import Stack
    from mapservice.robot import DEFAULT_MAP
    from mapservice.robot.map_upload import upload_map_if_fresh
    from mapservice.settings import Settings

    ros_map = load_ros_map(DEFAULT_MAP)
    defaults = Settings()
    env: dict[str, str] = {}
    if args.clients > defaults.foxglove_max_clients:  # the bench's clients are not refused
        env["MAPSERVICE_FOXGLOVE_MAX_CLIENTS"] = str(args.clients)
    channels = 3 * args.robots + 16  # a robot's pose, state and path; the shared channels
    if channels > defaults.foxglove_max_subscriptions:
        env["MAPSERVICE_FOXGLOVE_MAX_SUBSCRIPTIONS"] = str(channels)
    kafka = "" if args.kafka == "auto" else args.kafka
    stack = Stack(base / "live", mqtt=args.mqtt, apart=True, kafka=kafka, extra_env=env)
    doc: dict[str, Any] = {"robots": args.robots, "clients": args.clients, "settings": env}
    fleet = None
    driver = None
    try:
        doc["yardstick_ms"] = yardstick_ms()
        say(f"live: yardstick {doc['yardstick_ms']:.1f} ms; starting the stack as `up` does")
        stack.start_brokers_and_clickhouse(meta_for(ros_map))
        stack.start_apart(gateway=True)
        doc["kafka"], doc["mqtt"] = stack.kafka, args.mqtt
        upload_map_if_fresh(stack.settings(), stack.data_dir, ros_map, int(time.time() * 1000))
        say("live: warm-up (one robot until its poses are queryable)")
        warm_up(stack, ros_map)
        say(f"live: {args.robots} robots publishing over MQTT")
        fleet = RawFleet(stack.mqtt_url, ros_map, args.robots, nice=LOADGEN_NICE)
        fleet.start(None)
        driver = threading.Thread(target=fleet.run, name="loadgen", daemon=True)
        driver.start()
        time.sleep(SETTLE_S)
        api = psutil.Process(stack.procs["api"].pid)
        if args.baseline_seconds > 0:
            say(f"live: {args.baseline_seconds:.0f} s with no Foxglove client (the baseline)")
            t0, c0 = time.monotonic(), cpu_seconds(api)
            _sleep_alive(stack, args.baseline_seconds)
            doc["no_clients_api_cpu_percent"] = round(
                100 * (cpu_seconds(api) - c0) / (time.monotonic() - t0), 2
            )
        url = stack.foxglove_url + "/"
        say(f"live: {args.clients} clients connecting to {url}")
        log_path = base / "logs" / "foxglove-clients.log"
        with NodeClients(
            "live",
            url,
            "--clients",
            str(args.clients),
            "--pose-prefix",
            POSE_PREFIX,
            log_path=log_path,
        ) as clients:
            _wait_receiving(clients, args.clients)
            time.sleep(SETTLE_S)
            node = psutil.Process(clients.pid)
            meter = CpuMeter(stack.procs, [], fleet.pids)
            before = clients.send(op="start")
            start_ms = time.time_ns() // 1_000_000
            cpu0, node0, poses0 = meter.snapshot(), cpu_seconds(node), fleet.stats.poses
            t0 = time.monotonic()
            while (left := args.seconds - (time.monotonic() - t0)) > 0:
                _sleep_alive(stack, min(left, 5.0))
                p = clients.last("progress") or {}
                say(
                    f"live: {time.monotonic() - t0:4.0f}/{args.seconds:.0f} s, "
                    f"{p.get('connected', 0)} clients connected, received "
                    f"{sum(p.get('messages', [])):,} messages, published "
                    f"{fleet.stats.poses - poses0:,} poses"
                )
            clients.send(op="stop")
            cpu1, node1 = meter.snapshot(), cpu_seconds(node)
            window = (start_ms, time.time_ns() // 1_000_000 - DELIVERY_GRACE_MS)
            report = clients.wait_for(lambda e: e["event"] == "report", 60, before)
        published = [ts for kind, _, ts, _ in list(fleet.stats.published) if kind == "pose"]
        doc["poses_published_while_measured"] = fleet.stats.poses - poses0
        doc.update(live_figures(report, cpu0, cpu1, node1 - node0, published, window, doc))
    finally:
        if fleet is not None:
            fleet.stop()
        if driver is not None:
            driver.join(30)
        stack.stop()
    return doc


def live_figures(
    report: dict[str, Any],
    cpu0: dict[str, Any],
    cpu1: dict[str, Any],
    node_cpu_s: float,
    published_ts: list[int],
    window: tuple[int, int],
    doc: dict[str, Any],
) -> dict[str, Any]:
    """The live phase's figures from the clients' report and the CPU snapshots; the share
    of poses delivered over the poses whose timestamps lie in `window` (ms, inclusive)."""
    from mapservice.bench.ingest.cpu import CpuMeter

    wall = cpu1["_wall"] - cpu0["_wall"]
    api_cpu_s = cpu1["api"] - cpu0["api"]
    clients = report["clients"]
    messages = sum(c["messages"] for c in clients)
    latencies = [v for c in clients for v in c["latencies"]]
    seconds = report["seconds"]
    per_client = [c["messages"] / seconds for c in clients]
    lo, hi = window
    published = sum(1 for ts in published_ts if lo <= ts <= hi)
    received = [
        sum(1 for ts in c["pose_log_ms"] if lo <= ts <= hi) / published if published else 0.0
        for c in clients
    ]
    figures = {
        "seconds": round(wall, 1),
        "messages_received": messages,
        "api_cpu_s": round(api_cpu_s, 2),
        "api_cpu_percent": round(100 * api_cpu_s / wall, 2),
        "api_cpu_us_per_message": round(1e6 * api_cpu_s / messages, 2) if messages else None,
        "messages_per_s_per_client": [round(v, 1) for v in per_client],
        "messages_per_s_per_client_median": round(statistics.median(per_client), 1),
        "bytes_per_s_per_client_median": round(
            statistics.median(c["bytes"] / seconds for c in clients)
        ),
        "poses_published_in_window": published,
        "poses_received_fraction_min": round(min(received), 4),
        "poses_received_fraction_median": round(statistics.median(received), 4),
        "pose_latency_samples": len(latencies),
        "pose_latency_p50_ms": percentile(latencies, 50) if latencies else None,
        "pose_latency_p95_ms": percentile(latencies, 95) if latencies else None,
        "pose_latency_p99_ms": percentile(latencies, 99) if latencies else None,
        "pose_latency_max_ms": max(latencies, default=None),
        "clients_closed": [c["closed"] for c in clients if c["closed"]],
        "node_clients_cpu_percent": round(100 * node_cpu_s / wall, 1),
        "cpu_percent_of_one_core": {
            k_: round(v, 1) for k_, v in CpuMeter.percent(cpu0, cpu1).items()
        },
        "loadavg_after": os.getloadavg(),
    }
    if "no_clients_api_cpu_percent" in doc and messages:
        extra_s = api_cpu_s - doc["no_clients_api_cpu_percent"] / 100 * wall
        figures["marginal_cpu_us_per_message"] = round(1e6 * extra_s / messages, 2)
    return figures


def _wait_receiving(clients: NodeClients, k: int) -> None:
    """Until all `k` clients are connected and each received a message."""
    deadline = time.monotonic() + CONNECT_TIMEOUT_S
    while time.monotonic() < deadline:
        p = clients.last("progress")
        if p and p["connected"] == k and min(p["messages"]) > 0:
            return
        if clients.closed():
            raise RuntimeError(f"Foxglove clients closed: {clients.closed()[:3]}")
        time.sleep(0.5)
    raise RuntimeError(
        f"the {k} Foxglove clients were not all receiving within {CONNECT_TIMEOUT_S} s"
    )


def _sleep_alive(stack: Stack, seconds: float) -> None:
    """Sleeps, failing as soon as a component exited."""
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        for name, proc in stack.procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"{name} exited ({proc.returncode}); see {stack.log_dir}")
        time.sleep(min(left, 0.5))


# --- seek to first frame ------------------------------------------------------------------


def seek_phase(args: argparse.Namespace, base: Path, say: Progress) -> dict[str, Any]:
    from mapservice.bench.ui_setup import ApiProcess, load_or_reuse
    from mapservice.bench.yardstick import yardstick_ms
    from mapservice.local.embedded import free_port

    say(f"seek: loading {args.days} days of {args.seek_robots} robots (or reusing them)")
    t0 = time.perf_counter()
    end = time.time_ns() // 1_000_000 - 600_000
    loaded, reused = load_or_reuse(
        base, "bench_seek", args.days, args.seek_robots, end, reuse=bool(args.data_dir)
    )
    doc: dict[str, Any] = {
        "days": args.days,
        "robots": args.seek_robots,
        "poses": loaded.poses,
        "chunk_events": loaded.chunk_events,
        "reused": reused,
        "load_s": round(time.perf_counter() - t0, 1),
    }
    say(f"seek: history {'reused' if reused else 'loaded'} in {doc['load_s']:.0f} s")
    doc["yardstick_ms"] = yardstick_ms()
    port = free_port()
    env = {"MAPSERVICE_FOXGLOVE_PORT": str(port)}
    log_dir = base / "logs"
    with (
        ApiProcess(base / "ch", "bench_seek", log_dir / "api-foxglove.log", extra_env=env) as api,
        httpx.Client(base_url=api.url, timeout=120) as http,
        NodeClients(
            "seek", f"ws://127.0.0.1:{port}/replay", log_path=log_dir / "foxglove-clients.log"
        ) as client,
    ):
        info = client.wait_for(lambda e: e["event"] == "serverInfo", CONNECT_TIMEOUT_S)
        time.sleep(SETTLE_S)  # the session's own first picture (at the window's end) sent
        if "playbackControl" not in info["capabilities"]:
            raise RuntimeError(f"the replay server offers no playback control: {info}")
        lo = max(loaded.start_ms, info["start_ms"] + 60_000)  # the window moves on meanwhile
        hi = min(loaded.end_ms, info["end_ms"])
        if lo >= hi:
            raise SystemExit(
                "bench foxglove: the loaded history is outside the replay window (the "
                "retention); load a fresh one"
            )
        doc["window_ms"] = [lo, hi]
        rng = random.Random(args.seed)
        timed = []
        for i in range(args.seeks + 1):  # the first: cold, reported apart
            seek = _one_seek(client, http, rng.randrange(lo, hi))
            if i == 0:
                doc["first_seek"] = seek
            else:
                timed.append(seek)
            say(
                f"seek {i}/{args.seeks}{' (cold)' if i == 0 else ''}: T={seek['at_ms']}, "
                f"frame {seek['frame_ms']:.0f} ms ({seek['robots']} robots"
                + (f", {seek['missing']} missing)" if seek["missing"] else ")")
            )
        doc["server_errors"] = client.server_errors()[:10]
    frames = [s["frame_ms"] for s in timed if not s["missing"]]
    doc.update(
        {
            "seeks": timed,
            "incomplete": sum(1 for s in timed if s["missing"]),
            "frame_p50_ms": _r(percentile(frames, 50)) if frames else None,
            "frame_p95_ms": _r(percentile(frames, 95)) if frames else None,
            "frame_max_ms": _r(max(frames)) if frames else None,
            "answer_p50_ms": _r(percentile([s["answer_ms"] for s in timed], 50)) if timed else None,
            "grid_p50_ms": _r(percentile([s["grid_ms"] for s in timed], 50)) if timed else None,
            "loadavg_after": os.getloadavg(),
        }
    )
    return doc


def _one_seek(client: NodeClients, http: httpx.Client, at_ms: int) -> dict[str, Any]:
    """One paused seek to `at_ms`: when the floor and each robot standing at T arrived."""
    time.sleep(SEEK_GAP_S)
    before = client.send(op="seek", at_ms=at_ms)
    got = client.wait_for(
        lambda e: e["event"] == "seek" and e["at_ms"] == at_ms, SEEK_TIMEOUT_S, before
    )
    response = http.get("/api/v1/robots", params={"at": at_ms})
    response.raise_for_status()
    standing = [r["robotId"] for r in response.json()["robots"]]
    poses = got["poses"]
    missing = [r for r in standing if r not in poses]
    arrived = [poses[r] for r in standing if r in poses]
    return {
        "at_ms": at_ms,
        "robots": len(standing),
        "missing": len(missing),
        "missing_robots": missing[:5],
        "answer_ms": _r(got["answer_ms"]) if got["answer_ms"] is not None else None,
        "grid_ms": _r(got["grid_ms"]),
        "frame_ms": _r(max([got["grid_ms"], *arrived])),
    }


def _r(ms: float) -> float:
    return round(ms, 1)


def add_parser(kinds: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = kinds.add_parser(
        "foxglove",
        help="the Foxglove WebSocket server: live fan-out to Foxglove's npm client (CPU per "
        "message, messages/s, pose latency) and replay seeks to the first complete frame",
    )
    p.add_argument(
        "--robots", type=int, default=200, help="live robots over MQTT (a pose a second each)"
    )
    p.add_argument(
        "--clients", type=int, default=10, help="live Foxglove clients, each on every channel"
    )
    p.add_argument(
        "--seconds", type=float, default=60.0, help="seconds measured with the clients connected"
    )
    p.add_argument(
        "--baseline-seconds",
        type=float,
        default=30.0,
        help="seconds of the fleet with no client first, for the marginal CPU (0: none)",
    )
    p.add_argument(
        "--live",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="run the live fan-out phase (--no-live: only the seeks)",
    )
    p.add_argument("--mqtt", default="mosquitto", help="mosquitto, amqtt or an mqtt:// URL")
    p.add_argument(
        "--kafka",
        choices=["auto", "apache", "tansu"],
        default="auto",
        help="the embedded Kafka (auto: MAPSERVICE_EMBEDDED_KAFKA, apache where Java is)",
    )
    p.add_argument("--days", type=float, default=7.0, help="days of history loaded for the seeks")
    p.add_argument(
        "--seek-robots", type=int, default=200, help="robots in the history loaded for the seeks"
    )
    p.add_argument(
        "--seeks", type=int, default=30, help="random seeks timed, after one cold seek (0: none)"
    )
    p.add_argument("--seed", type=int, default=1, help="random seed of the seeks' instants")
    p.add_argument(
        "--data-dir",
        default=None,
        help=DATA_DIR_HELP + "; a history loaded there before (same --days and "
        "--seek-robots, by this bench or `bench ui`) is reused",
    )
    p.add_argument("--json", default=None, help="write the results as JSON to this file")
    p.set_defaults(func=main)
