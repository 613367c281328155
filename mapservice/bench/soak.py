"""`mapservice bench soak`: the embedded service under simulated robots for a long time, sampled.

One run starts the whole stack as `mapservice up` does (the embedded Kafka: Apache Kafka, or
tansu with `--kafka tansu`; the MQTT broker, `serve`, the gateway) on a fresh data directory, drives `--robots` robots with the 2019 workload
(robot/loadgen.py) for `--minutes`, and every `--sample-s` records, per component process:
resident memory and CPU share; the bytes on disk of the embedded Apache Kafka's log
and of ClickHouse's data; for the pipeline: events published and stored, dead
letters, and freshness (the age of the newest queryable pose: publish period plus the
pipeline's latency). A component that exits ends the run as a failure, with its log named.

The summary fits a line through each component's memory after the first tenth of the run
(start-up and caches filling) and states its growth per hour. tansu keeps every record in
memory (no retention, docs/embedded.md), so its growth is expected: it is reported
per stored event, with what a day and a week at this load would hold. Apache Kafka (a JVM
with a bounded heap) is judged like every other component; its log's growth on disk is
priced per stored event, up to what its retention lets it keep. Every other
component's growth of anonymous memory (resident minus file-backed pages, which are mapped
code such as chDB's library: bounded and reclaimable) is checked against
`--max-growth-mb-per-h` (the command fails when one exceeds it); serve's is also split into
ClickHouse's tracked memory and Python's allocated blocks. A run shorter than an hour says that it is not representative and is not judged.
"""

from __future__ import annotations

import json
import os
import statistics
import threading
import time
from pathlib import Path

import httpx
import psutil

from mapservice.bench.procstat import cpu_seconds, resident_mb
from mapservice.bench.workdir import DATA_DIR_HELP, bench_data_dir

HOUR_S = 3600.0
# tansu: memory storage, every record kept (docs/embedded.md); Apache Kafka is bounded.
EXPECTED_TO_GROW = {"tansu": {"kafka"}, "apache": set()}


def growth_per_hour(times_s: list[float], values: list[float]) -> float | None:
    """Least-squares slope of `values` over `times_s`, per hour; None below three points."""
    if len(times_s) < 3 or max(times_s) - min(times_s) <= 0:
        return None
    slope, _ = statistics.linear_regression(times_s, values)
    return slope * HOUR_S


def settle(samples: list[dict]) -> list[dict]:
    """The samples after the first tenth of the run (start-up, caches and pools filling)."""
    if not samples:
        return []
    end = samples[-1]["t_s"]
    return [s for s in samples if s["t_s"] >= end / 10]


def summarize(
    samples: list[dict], minutes: float, max_growth_mb_per_h: float, kafka: str = "tansu"
) -> dict:
    """Per component: memory first/last/max and growth per hour; pipeline totals; disk;
    verdicts. `kafka`: the embedded broker ("tansu" grows by design, "apache" is judged)."""
    expected = EXPECTED_TO_GROW.get(kafka, set())
    steady = settle(samples)
    components = sorted({name for s in samples for name in s["rss_mb"]})
    out: dict = {"components": {}, "representative": minutes >= 60, "kafka": kafka}
    for name in components:
        points = [(s["t_s"], s["rss_mb"][name]) for s in steady if name in s["rss_mb"]]
        rss = [s["rss_mb"][name] for s in samples if name in s["rss_mb"]]
        cpu = [s["cpu_percent"][name] for s in steady if name in s.get("cpu_percent", {})]
        # CPU at the start and at the end of the steady part: a component whose cost grows
        # with what it holds (tansu scanning its memory) shows it here.
        tenth = max(1, len(cpu) // 10)
        growth = growth_per_hour([t for t, _ in points], [v for _, v in points])
        # Judged on anonymous memory where it was sampled: resident file pages are mapped
        # code and files (chDB's 555 MB library in serve), bounded by their size and given
        # back under memory pressure; a leak is anonymous.
        anon = [(s["t_s"], s["anon_mb"][name]) for s in steady if name in s.get("anon_mb", {})]
        anon_growth = growth_per_hour([t for t, _ in anon], [v for _, v in anon])
        judged = anon_growth if anon_growth is not None else growth
        bounded = None if judged is None or name in expected else judged <= max_growth_mb_per_h
        out["components"][name] = {
            "rss_first_mb": rss[0] if rss else None,
            "rss_last_mb": rss[-1] if rss else None,
            "rss_max_mb": max(rss) if rss else None,
            "growth_mb_per_h": growth,
            "anon_first_mb": anon[0][1] if anon else None,
            "anon_last_mb": anon[-1][1] if anon else None,
            "anon_growth_mb_per_h": anon_growth,
            "cpu_median_percent": statistics.median(cpu) if cpu else None,
            "cpu_start_percent": statistics.median(cpu[:tenth]) if cpu else None,
            "cpu_end_percent": statistics.median(cpu[-tenth:]) if cpu else None,
            "growth_bounded": bounded,
        }
    if samples:
        last, first = samples[-1], steady[0] if steady else samples[0]
        stored = last["stored"] - first["stored"]
        out["stored_events"] = last["stored"]
        out["published_events"] = last["published"]
        out["dead_letters"] = last["dead_letters"]
        out["events_per_s"] = stored / max(1e-9, last["t_s"] - first["t_s"])
        fresh = [s["freshness_s"] for s in steady if s["freshness_s"] is not None]
        out["freshness_median_s"] = statistics.median(fresh) if fresh else None
        out["freshness_max_s"] = max(fresh) if fresh else None
        kafka_mem = out["components"].get("kafka", {})
        if (
            kafka == "tansu"
            and kafka_mem.get("growth_mb_per_h") is not None
            and out["events_per_s"] > 0
        ):
            per_event = kafka_mem["growth_mb_per_h"] * 1e6 / (out["events_per_s"] * HOUR_S)
            out["kafka_bytes_per_event"] = per_event
            out["kafka_mb_per_day"] = kafka_mem["growth_mb_per_h"] * 24
            out["kafka_mb_per_week"] = kafka_mem["growth_mb_per_h"] * 24 * 7
        out["disk"] = disk_summary(steady, out["events_per_s"])
        inside = [(x["t_s"], x["serve_inside"]) for x in steady if x.get("serve_inside")]
        if inside:
            times = [t for t, _ in inside]
            out["serve_inside"] = {
                key: {
                    "first": inside[0][1][key],
                    "last": inside[-1][1][key],
                    "growth_per_h": growth_per_hour(times, [v[key] for _, v in inside]),
                }
                for key in inside[0][1]
            }
    out["bounded"] = all(c["growth_bounded"] is not False for c in out["components"].values())
    return out


def disk_summary(steady: list[dict], events_per_s: float) -> dict:
    """Per directory sampled (`disk_mb`): first, last, growth per hour and, while events
    are stored, bytes per stored event."""
    out = {}
    for name in sorted({n for s in steady for n in s.get("disk_mb", {})}):
        points = [(s["t_s"], s["disk_mb"][name]) for s in steady if name in s.get("disk_mb", {})]
        growth = growth_per_hour([t for t, _ in points], [v for _, v in points])
        out[name] = {
            "first_mb": points[0][1],
            "last_mb": points[-1][1],
            "growth_mb_per_h": growth,
            "bytes_per_event": (
                growth * 1e6 / (events_per_s * HOUR_S)
                if growth is not None and events_per_s > 0
                else None
            ),
        }
    return out


def dir_mb(path: Path) -> float:
    """Bytes of the files under `path` (0 where it does not exist), in MB."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += os.stat(os.path.join(root, name)).st_blocks * 512
            except OSError:  # a segment deleted by retention while we walk
                pass
    return total / 1e6


def disk_dirs(data_dir: Path, kafka: str) -> dict[str, Path]:
    """The directories whose size on disk the soak samples."""
    dirs = {"clickhouse": data_dir / "clickhouse"}
    if kafka == "apache":
        dirs["kafka_log"] = data_dir / "kafka" / "log"
    return dirs


INSIDE_SERVE = {
    "mapservice_chdb_memory_tracked_bytes": ("chdb_mb", 1e-6),
    "mapservice_python_allocated_blocks": ("python_blocks_k", 1e-3),
}


def serve_inside(http: httpx.Client, api_url: str) -> dict[str, float] | None:
    """Where serve's memory is: ClickHouse's tracker (chDB lives in serve) and Python's
    allocator, from serve's /metrics; None if it does not answer."""
    from prometheus_client.parser import text_string_to_metric_families

    try:
        text = http.get(f"{api_url}/metrics").text
    except httpx.HTTPError:
        return None
    out = {}
    for family in text_string_to_metric_families(text):
        if family.name in INSIDE_SERVE and family.samples:
            key, scale = INSIDE_SERVE[family.name]
            out[key] = round(family.samples[0].value * scale, 3)
    return out or None


class Sampler:
    """CPU share and memory of each component process between two calls."""

    def __init__(self, procs: dict) -> None:
        self._procs = {name: psutil.Process(p.pid) for name, p in procs.items()}
        self._cpu = {name: cpu_seconds(p) for name, p in self._procs.items()}
        self._at = time.monotonic()

    def sample(self) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
        """(resident MB, anonymous resident MB, CPU %) per component since the last call."""
        now = time.monotonic()
        elapsed = max(1e-9, now - self._at)
        rss, anon, cpu = {}, {}, {}
        for name, proc in self._procs.items():
            cpu_s = cpu_seconds(proc)
            cpu[name] = 100 * (cpu_s - self._cpu[name]) / elapsed
            self._cpu[name] = cpu_s
            rss[name], anon[name] = resident_mb(proc)
        self._at = now
        return rss, anon, cpu


def freshness_s(http: httpx.Client, api_url: str, robot_id: str) -> float | None:
    """Seconds since the newest queryable pose of `robot_id` (None: none in the last minute)."""
    now_ms = int(time.time() * 1000)
    reply = http.get(
        f"{api_url}/api/v1/poses",
        params={"robotId": robot_id, "from": now_ms - 60_000, "to": now_ms + 1000},
    )
    reply.raise_for_status()
    times = [pose["ts_ms"] for pose in reply.json()]
    return (now_ms - max(times)) / 1000 if times else None


def run(args, console) -> dict:
    with bench_data_dir(args.data_dir, "bench-soak-") as data_dir:
        return _run(args, console, data_dir)


def _run(args, console, data_dir: Path) -> dict:
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.local.stack import Stack
    from mapservice.robot import DEFAULT_MAP
    from mapservice.robot.loadgen import RobotFleet

    ros_map = load_ros_map(DEFAULT_MAP)
    stack = Stack(data_dir, mqtt=args.mqtt, kafka="" if args.kafka == "auto" else args.kafka)
    settings = stack.settings()
    samples: list[dict] = []
    result: dict = {
        "data_dir": str(data_dir),
        "robots": args.robots,
        "minutes": args.minutes,
        "mqtt": args.mqtt,
        "kafka": stack.kafka,
        "samples": samples,
    }
    if stack.kafka == "apache":
        from mapservice.local.kafka_broker import kafka_version

        result["kafka_broker"] = {
            "version": kafka_version(),
            "heap_mb": settings.embedded_kafka_heap_mb,
            "retention_hours": settings.embedded_kafka_retention_hours,
            "retention_bytes_per_partition": settings.embedded_kafka_retention_bytes,
        }
    disks = disk_dirs(data_dir, stack.kafka)
    fleet = None
    try:
        with console.status(
            f"starting Kafka ({stack.kafka}), {args.mqtt}, server, gateway in {data_dir}..."
        ):
            stack.start_brokers()
            stack.publish_meta(meta_for(ros_map))
            stack.start_server()
            stack.start_gateway()
        fleet = RobotFleet(stack.mqtt_url, ros_map, args.robots, prefix="soak")
        driver = threading.Thread(
            target=fleet.run, args=(args.minutes * 60,), name="soak-fleet", daemon=True
        )
        sampler = Sampler(stack.procs)
        bench_proc = psutil.Process()
        http = httpx.Client(timeout=30)
        t0 = time.monotonic()
        driver.start()
        while driver.is_alive():
            driver.join(args.sample_s)
            for name, proc in stack.procs.items():
                if proc.poll() is not None:
                    raise RuntimeError(
                        f"{name} exited ({proc.returncode}) after "
                        f"{(time.monotonic() - t0) / 60:.1f} min; see {stack.log_dir}/"
                    )
            rss, anon, cpu = sampler.sample()
            stats = http.get(f"{stack.api_url}/api/v1/stats").json()
            sample = {
                "t_s": round(time.monotonic() - t0, 1),
                "rss_mb": rss,
                "anon_mb": anon,
                "cpu_percent": cpu,
                "disk_mb": {name: round(dir_mb(path), 2) for name, path in disks.items()},
                "bench_rss_mb": bench_proc.memory_info().rss / 1e6,
                "published": fleet.stats.poses + fleet.stats.chunks,
                "stored": stats["poses"] + stats["chunk_events"],
                "dead_letters": stats["dead_letters"],
                "freshness_s": freshness_s(http, stack.api_url, fleet.robots[0]),
                "serve_inside": serve_inside(http, stack.api_url),
            }
            samples.append(sample)
            console.print(
                f"{sample['t_s'] / 60:6.1f} min  stored {sample['stored']:>9,}  "
                f"dead letters {sample['dead_letters']}  freshness {sample['freshness_s']}s  "
                + "  ".join(f"{n} {rss[n]:.0f} MB {cpu[n]:.0f}%" for n in sorted(rss))
                + "  disk "
                + "  ".join(f"{n} {v:.0f} MB" for n, v in sample["disk_mb"].items())
            )
    finally:
        if fleet is not None:
            fleet.stop()
        stack.stop()
    result["summary"] = summarize(samples, args.minutes, args.max_growth_mb_per_h, stack.kafka)
    return result


def print_summary(console, result: dict, max_growth: float) -> None:
    s = result["summary"]
    if not s["representative"]:
        console.print(
            f"[yellow]A {result['minutes']:g}-minute run is not representative: a soak "
            "needs at least an hour; the figures below are indicative only.[/]"
        )
    console.print(
        f"{result['robots']} robots, {s.get('events_per_s', 0):.1f} events/s stored; "
        f"{s.get('stored_events', 0):,} stored of {s.get('published_events', 0):,} published; "
        f"dead letters {s.get('dead_letters', 0)}; freshness median "
        f"{s.get('freshness_median_s')} s, max {s.get('freshness_max_s')} s"
    )
    for name, c in s["components"].items():
        growth = c["growth_mb_per_h"]
        verdict = (
            "expected: keeps every record"
            if name in EXPECTED_TO_GROW.get(s["kafka"], ())
            else "bounded"
            if c["growth_bounded"]
            else f"over {max_growth:g} MB/h"
            if c["growth_bounded"] is False
            else "too few samples"
        )
        console.print(
            f"  {name:10s} RSS {c['rss_first_mb']:.0f} -> {c['rss_last_mb']:.0f} MB "
            f"(max {c['rss_max_mb']:.0f}), growth "
            f"{'n/a' if growth is None else f'{growth:+.1f} MB/h'}"
            + (
                f", anonymous {c['anon_first_mb']:.0f} -> {c['anon_last_mb']:.0f} MB "
                f"({c['anon_growth_mb_per_h']:+.1f} MB/h)"
                if c.get("anon_growth_mb_per_h") is not None
                else ""
            )
            + f" ({verdict}), "
            f"CPU median {c['cpu_median_percent'] or 0:.0f}% "
            f"({c['cpu_start_percent'] or 0:.0f}% at the start, {c['cpu_end_percent'] or 0:.0f}% at the end)"
        )
    for key, label, unit in (
        ("chdb_mb", "ClickHouse's tracked memory in serve", "MB"),
        ("python_blocks_k", "Python's allocated blocks in serve", "k"),
    ):
        inside = s.get("serve_inside", {}).get(key)
        if inside and inside["growth_per_h"] is not None:
            console.print(
                f"  {label}: {inside['first']:.1f} -> {inside['last']:.1f} {unit}, "
                f"growth {inside['growth_per_h']:+.1f} {unit}/h"
            )
    for name, d in s.get("disk", {}).items():
        growth = d["growth_mb_per_h"]
        console.print(
            f"  disk {name:10s} {d['first_mb']:.1f} -> {d['last_mb']:.1f} MB, growth "
            f"{'n/a' if growth is None else f'{growth:+.1f} MB/h'}"
            + (
                f", ~{d['bytes_per_event']:.0f} bytes per stored event"
                if d.get("bytes_per_event") is not None
                else ""
            )
        )
    broker = result.get("kafka_broker")
    if broker:
        console.print(
            f"  Apache Kafka {broker['version']}: heap at most {broker['heap_mb']} MB; "
            f"its log kept {broker['retention_hours']} h and at most "
            f"{broker['retention_bytes_per_partition'] / 1024**2:.0f} MiB per partition"
        )
    if "kafka_bytes_per_event" in s:
        console.print(
            f"  tansu holds ~{s['kafka_bytes_per_event']:.0f} bytes per event: "
            f"{s['kafka_mb_per_day']:.0f} MB a day, {s['kafka_mb_per_week']:.0f} MB a week "
            "at this load until `mapservice up` restarts"
        )


def add_parser(kinds) -> None:
    soak = kinds.add_parser(
        "soak",
        help="the embedded service under simulated robots for a long "
        "time: memory, CPU, freshness and errors over time",
    )
    soak.add_argument(
        "--minutes",
        type=float,
        default=60,
        help="how long the robots publish (under 60: reported as not representative)",
    )
    soak.add_argument(
        "--robots",
        type=int,
        default=20,
        help="simulated robots (each a pose a second and a chunk every five)",
    )
    soak.add_argument(
        "--mqtt", default="amqtt", help="amqtt (as `mapservice up`), mosquitto or an mqtt:// URL"
    )
    soak.add_argument(
        "--kafka",
        choices=("auto", "apache", "tansu"),
        default="auto",
        help="the embedded Kafka: apache (a KRaft node, log on disk, bounded heap), "
        "tansu (in memory) or auto (MAPSERVICE_EMBEDDED_KAFKA: apache where Java is)",
    )
    soak.add_argument("--sample-s", type=float, default=30, help="seconds between samples")
    soak.add_argument(
        "--max-growth-mb-per-h",
        type=float,
        default=20,
        help="memory growth per hour "
        "allowed to each component except tansu (which keeps every record); Apache Kafka's "
        "JVM is judged too",
    )
    soak.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    soak.add_argument("--json", default=None, help="write samples and summary as JSON to this file")
    soak.set_defaults(func=main)


def main(args) -> None:
    from rich.console import Console

    from mapservice.bench.machine import machine_facts

    console = Console()
    facts = machine_facts()
    result = run(args, console)
    result["machine"] = facts
    print_summary(console, result, args.max_growth_mb_per_h)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
        console.print(f"wrote {args.json}")
    # A short run's slope is mostly start-up noise: it is reported, not judged.
    if result["summary"]["representative"] and not result["summary"]["bounded"]:
        raise SystemExit("memory grew faster than --max-growth-mb-per-h; see the summary above")
