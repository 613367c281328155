"""`mapservice bench ingest`: the 2019 load test through the whole pipeline, measured.

One run:

1. start the whole stack (tansu, the MQTT broker, processors + API, gateway) on a fresh
   data directory and publish the map meta, as `mapservice up` does;
2. warm up: one extra robot publishes for a few seconds and the run waits until its
   messages are queryable, so the timed run starts on a pipeline that is consuming;
3. `RobotFleet` publishes the 2019 workload (one pose a second and one chunk every five
   seconds per robot) for `--seconds`, recording each message's publish wall time;
4. meanwhile a thread polls the API (`/api/v1/poses`, `/api/v1/chunk-events`) about every
   100 ms and notes when each (kind, robot, ts_ms) is first returned, and another listens
   on the live WebSocket, which the API sends an event on (stamping `sent_ms`) once its
   insert returned; the earlier of the two is when the event was known queryable;
5. after the fleet stops it waits until everything is queryable (or 60 s), scans the
   whole run window through the API to count lost and duplicated events, and reads
   `/api/v1/stats`;
6. it stops the stack, merges the ClickHouse parts (OPTIMIZE FINAL) and reads their
   size on disk.

CPU per component is the CPU time (user + system, including child processes) each
process used while the fleet ran, divided by the fleet's wall time: 100 % is one core.
"""

from __future__ import annotations

import gc
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import psutil

from mapservice.bench.procstat import resident_by_component, cpu_seconds
from mapservice.bench.yardstick import yardstick_ms

KEYS_PER_POSE = "pose"
KEYS_PER_CHUNK = "chunk"
WARMUP_PREFIX = "warmup"
POLL_INTERVAL_S = 0.1
MAX_WINDOW_MS = 30_000  # the sliding window never reaches further back than this
API_LIMIT = 100_000  # the API's maximum `limit`
POLL_LIMIT = 10_000  # rows per poll and kind: bounds the poller's read load while lagging
DRAIN_STALL_S = 20.0  # the drain ends when the store has counted nothing new for this long
DRAIN_MAX_S = 600.0  # and in any case after this long
LOADGEN_NICE = 10  # added to the load generator's threads' niceness (Linux: per thread)

TARGETS = {
    "robots": 1000,
    "lost": 0,
    "duplicated": 0,
    "p99_latency_s": 2.0,
    "bytes_per_robot_day": 1.5e6,
}
# Issue 16's live bounds: what a fleet must hold (`live_bounds`); --find-ceiling steps the
# fleet up until a step misses one.
SCHEDULE_MIN_PERCENT = 99.5  # the load generator kept its schedule (else it was the limit)
SUSTAINED_MIN_FRACTION = 0.99
PUSH_P99_MAX_S = 1.0
POLL_P99_MAX_S = 2.0
SMALL_FLEET = 1000  # up to this many robots, p99 (push or poll) at most SMALL_FLEET_P99_S
SMALL_FLEET_P99_S = 0.3
MIN_JUDGED_S = 60.0  # shorter runs are reported, not judged: start-up noise dominates them
BASELINE_2019 = {"robots": 20, "bytes_per_day": 300e6, "bytes_per_robot_day": 15e6,
                 "store": "Elasticsearch"}


# --- machine facts ------------------------------------------------------------------


def _first_line(cmd: list[str]) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unknown ({exc})"
    text = (out.stdout or out.stderr).strip().splitlines()
    return text[0] if text else "unknown"


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo ("unknown" elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def embedded_kafka_fact() -> str:
    """Which Kafka the runs' stacks embed (MAPSERVICE_EMBEDDED_KAFKA)."""
    from mapservice.local import kafka_broker
    from mapservice.settings import Settings

    if kafka_broker.embedded_choice(Settings().embedded_kafka) == "apache":
        return f"Apache Kafka {kafka_broker.kafka_version()} (one KRaft node)"
    return "tansu (memory)"


def machine_facts() -> dict:
    model = cpu_model()
    try:
        from mapservice.local.embedded import tansu_binary

        tansu = _first_line([str(tansu_binary()), "--version"])
    except Exception as exc:  # noqa: BLE001 - a fact we could not read, not a failure
        tansu = f"unknown ({exc})"
    mosquitto_bin = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    mosquitto = _first_line([mosquitto_bin, "-h"]) if os.path.exists(mosquitto_bin) else "not installed"
    versions = {}
    for dist in ("chdb", "clickhouse-connect", "faust-streaming", "aiokafka", "confluent-kafka",
                 "paho-mqtt", "fastapi", "uvicorn"):
        try:
            from importlib.metadata import version

            versions[dist] = version(dist)
        except Exception:  # noqa: BLE001
            versions[dist] = "unknown"
    return {
        "nproc": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu_model": model,
        "ram_bytes": psutil.virtual_memory().total,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "tansu": tansu,
        "kafka": embedded_kafka_fact(),
        "mosquitto": mosquitto,
        "packages": versions,
        "loadavg_at_start": os.getloadavg(),
        "git": _git_state(),
    }


def _git_state() -> dict:
    from mapservice.local.checkout import ROOT as root

    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=10, check=False).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain"],
                               capture_output=True, text=True, timeout=10, check=False).stdout.splitlines()
    except (OSError, subprocess.TimeoutExpired):
        return {}
    return {"head": head, "uncommitted": [line.strip() for line in dirty]}


# --- CPU accounting -----------------------------------------------------------------


def _thread_cpu_seconds(native_id: int | None) -> float:
    if native_id is None:
        return 0.0
    for t in psutil.Process().threads():
        if t.id == native_id:
            return t.user_time + t.system_time
    return 0.0


class CpuMeter:
    """CPU seconds per stack component, this process and its latency probes' threads, and
    the machine."""

    def __init__(self, procs: dict, probe_native_ids: list[int | None],
                 loadgen_pids: list[int] = ()) -> None:
        self.procs = {name: psutil.Process(p.pid) for name, p in procs.items()}
        self.probe_native_ids = probe_native_ids  # the latency poller's and listener's threads
        self.loadgen = [psutil.Process(pid) for pid in loadgen_pids]  # RawFleet's workers
        self.me = psutil.Process()

    def snapshot(self) -> dict:
        machine = psutil.cpu_times()
        field = lambda name: getattr(machine, name, 0.0)  # fields vary by OS
        snap = {name: cpu_seconds(p) for name, p in self.procs.items()}
        me = self.me.cpu_times()
        snap["_bench_process"] = me.user + me.system
        snap["_poller_thread"] = sum(_thread_cpu_seconds(i) for i in self.probe_native_ids)
        snap["_loadgen_workers"] = sum(cpu_seconds(p) for p in self.loadgen)
        # Linux counts guest time inside user time, so it is not added again.
        snap["_machine_processes"] = field("user") + field("nice") + field("system")
        snap["_machine_irq"] = field("irq") + field("softirq")
        snap["_machine_steal"] = field("steal")  # taken by the hypervisor for other VMs
        snap["_wall"] = time.monotonic()
        return snap

    @staticmethod
    def percent(before: dict, after: dict, workers_cpu_s: float | None = None) -> dict:
        """Shares of one core; `workers_cpu_s`: the load fleet's workers' own count of their
        CPU time (they exit when the fleet is done, before `after` could sample them)."""
        wall = after["_wall"] - before["_wall"]
        pct = {k: 100.0 * (after[k] - before[k]) / wall for k in before if not k.startswith("_")}
        for name in [k for k in pct if k.startswith("gateway-")]:  # replicas count as the gateway
            pct["gateway"] += pct.pop(name)
        bench = 100.0 * (after["_bench_process"] - before["_bench_process"]) / wall
        poller = 100.0 * (after["_poller_thread"] - before["_poller_thread"]) / wall
        workers = 100.0 * (workers_cpu_s if workers_cpu_s is not None else
                           after.get("_loadgen_workers", 0.0) - before.get("_loadgen_workers", 0.0)) / wall
        pct["stack_total"] = sum(pct.values())
        # The load generator: its worker processes (RawFleet) and its part of this process
        # (paho's RobotFleet; or RawFleet collecting the acknowledged messages).
        pct["loadgen"] = bench - poller + workers
        pct["loadgen_workers"] = workers
        pct["latency_probes"] = poller
        delta = {k: 100.0 * (after[k] - before[k]) / wall
                 for k in ("_machine_processes", "_machine_irq", "_machine_steal")}
        # Whatever else ran on the machine meanwhile (other users' work competes for the cores).
        pct["other_processes"] = delta["_machine_processes"] - pct["stack_total"] - bench - workers
        pct["irq_softirq"] = delta["_machine_irq"]
        pct["steal"] = delta["_machine_steal"]
        pct["machine_busy_all_cores"] = sum(delta.values())
        pct["wall_s"] = wall
        return pct


def cpu_us_per_event(cpu_pct: dict, events: int, wall_s: float) -> dict:
    """Each component's CPU per published event, in µs: its share of a core over the
    fleet's wall time divided by the events published in it."""
    if not events or wall_s <= 0:
        return {}
    per_s = events / wall_s
    skip = ("other_processes", "irq_softirq", "steal", "machine_busy_all_cores", "wall_s")
    return {k: v * 1e4 / per_s for k, v in cpu_pct.items() if k not in skip}


# --- the poller -----------------------------------------------------------------------


Key = tuple[str, str, int]  # (kind, robot id, event time ms)


class QueryablePoller(threading.Thread):
    """Polls the API and records when each event first becomes queryable.

    The window starts at the event time of the oldest published event of that kind not
    yet seen (never more than 30 s back) and ends in the future, so each poll reads only
    what may still be missing instead of a fixed 30 s of history.
    """

    def __init__(self, api_url: str, published: list, interval_s: float = POLL_INTERVAL_S) -> None:
        super().__init__(name="latency-poller", daemon=True)
        self.api_url = api_url
        self.published = published
        self.interval_s = interval_s
        self.first_seen: dict[Key, float] = {}
        # The gateway's receive time of each event seen (same machine, same clock): splits
        # publish -> queryable into MQTT + gateway, and Kafka + processors + store.
        self.received_at: dict[Key, float] = {}
        # The start of the last poll of the same kind that did not return the key yet:
        # the event became queryable after that moment (a lower bound on its latency).
        self.not_seen_at: dict[Key, float] = {}
        self.pending: dict[Key, int] = {}
        self.censored: set[Key] = set()  # left the window unseen: latency > MAX_WINDOW_MS
        self._consumed = 0
        self.polls = 0
        self.poll_seconds: list[float] = []
        self.cycle_seconds: list[float] = []  # start to start: how late a poll can see an event
        self._last_start: float | None = None
        self.window_rows: list[int] = []
        self.in_response_duplicates = 0
        self.truncated_polls = 0
        self.errors = 0
        self.last_error = ""
        self._halt = threading.Event()
        self._ready = threading.Event()

    def stop(self) -> None:
        self._halt.set()

    def _take_published(self) -> None:
        n = len(self.published)  # the fleet only appends; entries up to n are complete
        for kind, robot, ts, _wall in self.published[self._consumed:n]:
            key = (kind, robot, ts)
            if key not in self.first_seen:
                self.pending[key] = ts
        self._consumed = n

    def _get(self, client: httpx.Client, path: str, f: int, t: int) -> tuple[list, float, float]:
        asked_at = time.time()
        r = client.get(f"{self.api_url}{path}", params={"from": f, "to": t, "limit": POLL_LIMIT})
        seen_at = time.time()
        r.raise_for_status()
        return r.json(), asked_at, seen_at

    def run(self) -> None:
        self._ready.set()
        with httpx.Client(timeout=30) as client:
            while not self._halt.is_set():
                started = time.monotonic()
                self._take_published()
                now_ms = time.time_ns() // 1_000_000
                oldest_allowed = now_ms - MAX_WINDOW_MS
                for key in [k for k, ts in self.pending.items() if ts < oldest_allowed]:
                    del self.pending[key]  # left the window unseen; the final scan decides
                    self.censored.add(key)
                if self._last_start is not None:
                    self.cycle_seconds.append(started - self._last_start)
                self._last_start = started
                truncated = False
                try:
                    rows = 0
                    for kind, path in ((KEYS_PER_POSE, "/api/v1/poses"),
                                       (KEYS_PER_CHUNK, "/api/v1/chunk-events")):
                        # Per kind: chunks and poses are stored by different agents, and a
                        # chunk still on its way must not widen the (larger) pose window.
                        lower = min((ts for k, ts in self.pending.items() if k[0] == kind),
                                    default=now_ms - 1000)
                        f, t = max(lower, oldest_allowed), now_ms + 5000
                        body, asked_at, seen_at = self._get(client, path, f, t)
                        rows += len(body)
                        # Rows come in event-time order: when the limit cut the answer, only
                        # pending events up to the last row returned were looked for.
                        examined_to = t
                        if len(body) >= POLL_LIMIT:
                            self.truncated_polls += 1
                            truncated = True
                            examined_to = body[-1]["ts_ms"]
                        in_this: set[Key] = set()
                        for row in body:
                            key = (kind, row["robotId"], row["ts_ms"])
                            if key in in_this:
                                self.in_response_duplicates += 1
                            in_this.add(key)
                            if key not in self.first_seen:
                                self.first_seen[key] = seen_at
                                self.received_at[key] = row["receive_time_ms"] / 1000
                                self.pending.pop(key, None)
                        for key, ts in self.pending.items():
                            if key[0] == kind and ts < examined_to:
                                self.not_seen_at[key] = asked_at
                    self.polls += 1
                    self.window_rows.append(rows)
                    self.poll_seconds.append(time.monotonic() - started)
                except (httpx.HTTPError, ValueError) as exc:
                    self.errors += 1
                    self.last_error = str(exc)[:200]
                # Every ~100 ms from the start of the last poll: the gap between polls is
                # this instrument's resolution, so a slow poll is not followed by a wait as
                # long again (that stretched the cycle up to 1 s at 5,000 robots; BENCHMARKS.md,
                # session 19). Only a poll cut at the row limit (a backlog wider than one
                # read) backs off to half the time, so a lagging pipeline does not get a
                # read load of its own.
                took = time.monotonic() - started
                self._halt.wait(max(self.interval_s - took, took if truncated else 0.0))


_LIVE_KINDS = {"pose": KEYS_PER_POSE, "chunk": KEYS_PER_CHUNK}


class LiveListener(threading.Thread):
    """Notes when the API sent each event on its live WebSocket (`/api/v1/live`).

    The history sink pushes a batch live only after its insert returned, so an event is
    queryable by the time the API sends it (`sent_ms`, stamped by the server on the same
    clock): an upper bound on publish -> queryable as tight as the push itself, where a
    poll adds up to a poll cycle and its own duration. The server's stamp, not this
    thread's receive time, because this process also runs the load generator's 1,000
    robots and a thread here waits its turn for the GIL. It also stands for a live UI
    watching the floor, which production has anyway, and asks for batched frames as the
    UI does (`?batch=true`: a JSON array of events per message, each with its `sent_ms`).
    """

    def __init__(self, api_url: str) -> None:
        super().__init__(name="latency-live-listener", daemon=True)
        self.ws_url = "ws" + api_url.removeprefix("http") + "/api/v1/live?batch=true"
        self.pushed_at: dict[Key, float] = {}
        self.messages = 0
        self.errors = 0
        self.last_error = ""
        self.connected = threading.Event()
        self._halt = threading.Event()

    def stop(self) -> None:
        self._halt.set()

    def run(self) -> None:
        from websockets.sync.client import connect

        try:
            with connect(self.ws_url, max_size=None, open_timeout=10, close_timeout=1) as ws:
                self.connected.set()
                while not self._halt.is_set():
                    try:
                        raw = ws.recv(timeout=0.5)
                    except TimeoutError:
                        continue
                    self.note(raw)
        except Exception as exc:  # noqa: BLE001 - reported with the results, the poll still counts
            self.errors += 1
            self.last_error = str(exc)[:200]
        finally:
            self.connected.set()  # never leave a waiter hanging

    def note(self, raw: str | bytes) -> None:
        """Notes the send time of each event in one message: a batched frame (a JSON
        array) or a single event (a server from before batching)."""
        data = json.loads(raw)
        for m in data if isinstance(data, list) else [data]:
            self.messages += 1  # events, whichever way they were framed
            kind = _LIVE_KINDS.get(m.get("type"))
            if kind is not None:
                self.pushed_at.setdefault((kind, m["robotId"], m["ts_ms"]), m["sent_ms"] / 1000)


class DrainWatch:
    """When the drain after the fleet stops is over: drained once the store counts every
    expected event; given up once its counts have not grown for DRAIN_STALL_S (what is
    missing then is lost, not late) or after DRAIN_MAX_S in all."""

    def __init__(self, expected: dict[str, int], stall_s: float = DRAIN_STALL_S,
                 max_s: float = DRAIN_MAX_S) -> None:
        self.expected = expected
        self.stall_s, self.max_s = stall_s, max_s
        self.drained_s: float | None = None
        self._last_total = -1
        self._last_growth_s = 0.0

    def observe(self, elapsed_s: float, counts: dict[str, int]) -> None:
        if all(counts[k] >= n for k, n in self.expected.items()):
            self.drained_s = elapsed_s
        total = sum(counts[k] for k in self.expected)
        if total > self._last_total:
            self._last_total, self._last_growth_s = total, elapsed_s

    def given_up(self, elapsed_s: float) -> bool:
        if self.drained_s is not None:
            return elapsed_s - self.drained_s > self.stall_s  # the poller had its moment
        return elapsed_s >= self.max_s or elapsed_s - self._last_growth_s >= self.stall_s


def counter_by_label(text: str, counter: str, label: str) -> dict[str, float]:
    """A Prometheus counter's `<counter>_total` samples in a /metrics text, summed per value
    of one label (an unlabelled sample counts under "")."""
    from prometheus_client.parser import text_string_to_metric_families

    out: dict[str, float] = {}
    for family in text_string_to_metric_families(text):
        if family.name != counter:
            continue
        for sample in family.samples:
            if sample.name == f"{counter}_total":
                key = sample.labels.get(label, "")
                out[key] = out.get(key, 0.0) + sample.value
    return out


def gateway_acks(health_ports: list[int]) -> list[float]:
    """Each gateway's messages handled and confirmed by Kafka so far (accepted and rejected,
    `mapservice_gateway_messages_total` on its health port's /metrics)."""
    counts = []
    for port in health_ports:
        text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text
        counts.append(sum(counter_by_label(text, "mapservice_gateway_messages", "outcome").values()))
    return counts


# The server's store thread, stage by stage: each stage's histogram (one observation per
# call; batch_events observes each batch's size).
STORE_STAGES = {"insert": "mapservice_sink_insert_seconds",
                "conflicts_check": "mapservice_conflicts_check_seconds",
                "conflicts_write": "mapservice_conflicts_write_seconds",
                "derive_views": "mapservice_sink_derive_views_seconds",
                "batch_events": "mapservice_sink_batch_events"}


def histogram_totals(text: str) -> dict[str, tuple[float, float]]:
    """The STORE_STAGES histograms' (count, sum) in a /metrics text (absent ones: 0, 0)."""
    from prometheus_client.parser import text_string_to_metric_families

    wanted = set(STORE_STAGES.values())
    out = {name: (0.0, 0.0) for name in wanted}
    for family in text_string_to_metric_families(text):
        if family.name in wanted:
            count = sum(s.value for s in family.samples if s.name == f"{family.name}_count")
            total = sum(s.value for s in family.samples if s.name == f"{family.name}_sum")
            out[family.name] = (count, total)
    return out


def store_stages(before: dict[str, tuple[float, float]], after: dict[str, tuple[float, float]],
                 wall_s: float) -> dict:
    """What the store thread spent between two scrapes, per stage: calls, mean ms per call
    and its share of the wall time; and the batches' mean size in events."""
    out: dict = {}
    for stage, metric in STORE_STAGES.items():
        calls = after[metric][0] - before[metric][0]
        total = after[metric][1] - before[metric][1]
        if stage == "batch_events":
            out["batches"] = calls
            out["events_per_batch"] = total / calls if calls else None
        else:
            out[stage] = {"calls": calls, "mean_ms": 1000 * total / calls if calls else None,
                          "busy_percent": 100 * total / wall_s if wall_s > 0 else None}
    return out


def server_metrics(api_url: str) -> str:
    """The server's /metrics text: one scrape serves the store stages and the offset gaps."""
    return httpx.get(f"{api_url}/metrics", timeout=10).text


def history_offset_gaps(text: str) -> dict[str, float]:
    """The history consumer's offset gaps so far (`mapservice_consumer_offset_gaps_total` in
    the server's /metrics text): read again, or accepted as lost after its rereads ran out."""
    gaps = counter_by_label(text, "mapservice_consumer_offset_gaps", "outcome")
    return {"reread": gaps.get("reread", 0.0), "accepted": gaps.get("accepted", 0.0)}


def queryable_times(first_polled: dict[Key, float], pushed: dict[Key, float]) -> dict[Key, float]:
    """Per event, the earliest moment it is known to be queryable: the end of the first
    poll that returned it or the sending of its live push, whichever came first."""
    out = dict(first_polled)
    for key, at in pushed.items():
        if at < out.get(key, INF):
            out[key] = at
    return out


# --- scanning and storage -------------------------------------------------------------


def _scan(client: httpx.Client, api_url: str, path: str, f: int, t: int) -> list[dict]:
    """Every row in [f, t), splitting the window when it would hit the API's limit."""
    r = client.get(f"{api_url}{path}", params={"from": f, "to": t, "limit": API_LIMIT})
    r.raise_for_status()
    body = r.json()
    if len(body) < API_LIMIT or t - f <= 1:
        return body
    mid = (f + t) // 2
    return _scan(client, api_url, path, f, mid) + _scan(client, api_url, path, mid, t)


def scan_run(api_url: str, f: int, t: int, slice_ms: int) -> dict[str, list[Key]]:
    out: dict[str, list[Key]] = {KEYS_PER_POSE: [], KEYS_PER_CHUNK: []}
    with httpx.Client(timeout=120) as client:
        for start in range(f, t, slice_ms):
            end = min(start + slice_ms, t)
            for kind, path in ((KEYS_PER_POSE, "/api/v1/poses"),
                               (KEYS_PER_CHUNK, "/api/v1/chunk-events")):
                out[kind].extend((kind, row["robotId"], row["ts_ms"])
                                 for row in _scan(client, api_url, path, start, end))
    return out


def storage_report(data_dir: Path) -> dict:
    """Runs in a child process: chDB opens one directory per process."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.settings import Settings

    store = ClickHouseStore(Settings(data_dir=data_dir).resolved_clickhouse_dsn)
    db = store.database
    try:
        raw = {t: store._rows(f"SELECT count() FROM {db}.{t}", {})[0][0]
               for t in ("poses", "chunk_events", "chunk_contents")}
        parts_before = {t: int(n) for t, n in store._rows(
            "SELECT table, count() FROM system.parts WHERE database = {d:String} AND active "
            "GROUP BY table", {"d": db})}
        store.optimize()
        merged = {t: store._rows(f"SELECT count() FROM {db}.{t}", {})[0][0]
                  for t in ("poses", "chunk_events", "chunk_contents")}
        tables = store.storage_bytes()
        columns = _column_bytes(store, db)
    finally:
        store.close()
    return {"raw_rows_before_merge": raw, "rows_after_merge": merged,
            "active_parts_before_merge": parts_before, "table_bytes": tables,
            "column_compressed_bytes": columns}


def _column_bytes(store, db: str) -> dict[str, int]:
    """Compressed bytes per column (diagnostic only, not counted in the totals).

    Short runs leave compact parts (all columns in one file), which report no per-column
    sizes, so the event tables are copied into a scratch database forced to wide parts.
    """
    scratch = "bench_scratch"
    with store._lock:
        c = store.client
        c.command(f"DROP DATABASE IF EXISTS {scratch}")
        c.command(f"CREATE DATABASE {scratch}")
        try:
            for t in ("poses", "chunk_events"):
                c.command(f"CREATE TABLE {scratch}.{t} AS {db}.{t}")
                c.command(f"ALTER TABLE {scratch}.{t} MODIFY SETTING min_bytes_for_wide_part = 0, "
                          "min_rows_for_wide_part = 0")
                c.command(f"INSERT INTO {scratch}.{t} SELECT * FROM {db}.{t}")
                c.command(f"OPTIMIZE TABLE {scratch}.{t} FINAL")
            rows = c.query(
                "SELECT table, column, sum(column_data_compressed_bytes), "
                "sum(column_data_uncompressed_bytes) FROM system.parts_columns "
                f"WHERE database = '{scratch}' AND active GROUP BY table, column").result_rows
        finally:
            c.command(f"DROP DATABASE IF EXISTS {scratch}")
    return {f"{t}.{col}": {"compressed": int(b), "uncompressed": int(u)} for t, col, b, u in rows}


def _storage_main(data_dir: str, out_file: str) -> None:
    Path(out_file).write_text(json.dumps(storage_report(Path(data_dir))))


def measure_storage(data_dir: Path) -> dict:
    out = data_dir / "storage.json"
    code = ("import sys; from mapservice.bench.ingest import _storage_main; "
            "_storage_main(sys.argv[1], sys.argv[2])")
    done = subprocess.run([sys.executable, "-c", code, str(data_dir), str(out)],
                          capture_output=True, text=True, timeout=900, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"storage measurement failed:\n{done.stderr[-2000:]}")
    return json.loads(out.read_text())


# --- one run ----------------------------------------------------------------------------

INF = float("inf")


def _latencies(queryable_at: dict[Key, float], not_seen_at: dict[Key, float],
               keys: dict[Key, float]) -> tuple[list[float], list[float]]:
    """Per published event: (upper, lower) bound of publish -> queryable, in seconds.

    Upper: the first moment it was known queryable (`queryable_times`; for a polled event
    that includes up to one poll interval and the poll's own duration). Lower: the start
    of the last poll that did not return it. Events never seen inside the 30 s window
    count as infinite, so they push the percentiles up instead of vanishing from them.
    """
    upper, lower = [], []
    for key, wall in keys.items():
        seen = queryable_at.get(key)
        if seen is None:
            upper.append(INF)
            lower.append(INF)
        else:
            upper.append(seen - wall)
            lower.append(min(seen - wall, max(0.0, not_seen_at.get(key, wall) - wall)))
    return upper, lower


def _stage_latencies(received_at: dict[Key, float], queryable_at: dict[Key, float],
                     keys: dict[Key, float]) -> dict:
    """Where the time goes, per event seen: publish -> gateway receive (Mosquitto, the
    gateway's MQTT client) and gateway receive -> queryable (Kafka produce, tansu, the
    history consumer, the insert, the push or poll)."""
    to_gateway, after_gateway = [], []
    for key, wall in keys.items():
        received = received_at.get(key)
        if received is not None and key in queryable_at:
            # The gateway stamps whole milliseconds (floored); floor the publish time the
            # same way, or a sub-millisecond hop comes out negative.
            to_gateway.append(received - math.floor(wall * 1000) / 1000)
            after_gateway.append(queryable_at[key] - received)
    return {"publish_to_gateway_p50_s": _pct(to_gateway, 50),
            "publish_to_gateway_p99_s": _pct(to_gateway, 99),
            "gateway_to_queryable_p50_s": _pct(after_gateway, 50),
            "gateway_to_queryable_p99_s": _pct(after_gateway, 99)}


def _pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)  # nearest rank: the smallest value with q % of the values at or below it
    return s[min(len(s) - 1, max(0, math.ceil(q / 100.0 * len(s)) - 1))]


def _status_line(run: int, runs: int, phase: str, elapsed: float, seconds: float, fleet,
                 poller: QueryablePoller | None, started_wall: float) -> str:
    from rich.markup import escape

    pub = fleet.stats.poses + fleet.stats.chunks
    seen = len(poller.first_seen) if poller else 0
    span = max(time.time() - started_wall, 1e-6)
    poll = poller.poll_seconds[-1] * 1000 if poller and poller.poll_seconds else 0.0
    return escape(
        f"run {run}/{runs} {phase} {elapsed:5.1f}/{seconds:.0f} s | published {pub:,} "
        f"({fleet.stats.poses:,} poses, {fleet.stats.chunks:,} chunks, {pub / span:,.0f}/s) | "
        f"queryable {seen:,} ({seen / span:,.0f}/s) | not yet {pub - seen:,} | "
        f"last poll {poll:.0f} ms")


def run_once(args, data_dir: Path, run: int, runs: int, console) -> dict:
    from rich.live import Live

    from mapservice.robot import DEFAULT_MAP
    from mapservice.robot.loadgen import RobotFleet
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.local.stack import Stack

    data_dir.mkdir(parents=True, exist_ok=True)
    ros_map = load_ros_map(DEFAULT_MAP)
    gateways = getattr(args, "gateways", 1)
    # `kafka`: "apache" or "tansu" (bench/brokers.py runs both); unset: the setting's choice.
    stack = Stack(data_dir, mqtt=args.mqtt, gateways=gateways, kafka=getattr(args, "kafka", ""))
    result: dict = {"data_dir": str(data_dir), "gateways": gateways}
    poller: QueryablePoller | None = None
    listener: LiveListener | None = None
    try:
        # Before the stack starts: the machine's speed right now, to compare runs by.
        result["yardstick_ms"] = yardstick_ms()
        t_start = time.monotonic()
        with console.status(f"run {run}/{runs}: starting Kafka ({stack.kafka}), {args.mqtt}, server, "
                            f"{gateways} gateway(s)..."):
            stack.start_brokers()
            stack.publish_meta(meta_for(ros_map))
            stack.start_server()
            stack.start_gateways()
        result["stack_start_s"] = time.monotonic() - t_start

        # Warm-up: proves MQTT -> gateway -> Kafka -> processors -> ClickHouse -> API is live.
        with console.status(f"run {run}/{runs}: warm-up (waiting for the pipeline to consume)..."):
            warm = RobotFleet(stack.mqtt_url, ros_map, 1, prefix=WARMUP_PREFIX, record=True, seed=1)
            warm.run(5.5)  # five poses and one chunk
            warm_keys = {(k, r, ts) for k, r, ts, _ in warm.stats.published}
            warm_poller = QueryablePoller(stack.api_url, warm.stats.published, interval_s=0.25)
            warm_poller.start()
            deadline = time.monotonic() + 120
            while not warm_keys <= warm_poller.first_seen.keys():
                if time.monotonic() > deadline:
                    warm_poller.stop()
                    raise RuntimeError(f"warm-up events not queryable after 120 s; see {stack.log_dir}")
                time.sleep(0.2)
            warm_poller.stop()
            warm_poller.join()
        result["warmup_s"] = time.monotonic() - t_start - result["stack_start_s"]

        loadgen = getattr(args, "loadgen", "raw")
        if getattr(args, "workload", "2019") == "vda5050":  # VDA 5050 vehicles (vda_fleet.py)
            from mapservice.bench.vda_fleet import VdaFleet

            loadgen, fleet = "vda5050", VdaFleet(stack.mqtt_url, ros_map, args.robots)
        elif loadgen == "raw":
            from mapservice.robot.rawfleet import RawFleet

            # Worker processes at a lower priority: they stand for robots on other machines.
            fleet = RawFleet(stack.mqtt_url, ros_map, args.robots,
                             processes=getattr(args, "loadgen_processes", None), nice=LOADGEN_NICE,
                             aligned_chunks=getattr(args, "aligned_chunks", False))
            with console.status(f"run {run}/{runs}: starting the load fleet's workers..."):
                fleet.start(args.seconds)
        else:
            fleet = RobotFleet(stack.mqtt_url, ros_map, args.robots, record=True,
                               aligned_chunks=getattr(args, "aligned_chunks", False))
        # The run's bookkeeping (a few hundred thousand keys and times, no cycles) made the
        # cyclic collector stop this process for 0.2-0.4 s every ~2 s late in a 5,000-robot
        # run, and the poller with it: the poll figure then measured those pauses.
        gc.disable()
        poller = QueryablePoller(stack.api_url, fleet.stats.published, args.poll_interval)
        poller.start()
        poller._ready.wait(5)
        listener = LiveListener(stack.api_url)
        listener.start()
        listener.connected.wait(15)
        meter = CpuMeter(stack.procs, [poller.native_id, listener.native_id],
                         getattr(fleet, "pids", []))
        fleet_error: list[BaseException] = []

        def drive() -> None:
            try:
                # The fleet stands for 1,000 robots that are not on this machine: at a lower
                # priority (its threads only; paho's network thread inherits it) it does not
                # take CPU from the system under test. Whether it still kept its schedule is
                # checked: published events/s against the offered load.
                try:
                    os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), LOADGEN_NICE)
                except (AttributeError, OSError):
                    pass
                fleet.run(args.seconds)
            except BaseException as exc:  # noqa: BLE001 - reported by the main thread
                fleet_error.append(exc)

        driver = threading.Thread(target=drive, name="loadgen", daemon=True)
        acked_before = gateway_acks(stack.gateway_health_ports)
        stages_before = histogram_totals(server_metrics(stack.api_url))
        stages_t0 = time.monotonic()
        cpu_before = meter.snapshot()
        started_wall = time.time()
        fleet_t0 = time.monotonic()
        driver.start()
        last_line = [0.0]

        def show(live, line: str) -> None:
            live.update(line)
            if not console.is_terminal and time.monotonic() - last_line[0] >= 10:
                console.print(line)  # a log file gets a line every 10 s instead
                last_line[0] = time.monotonic()

        with Live(console=console, refresh_per_second=4, transient=True) as live:
            while driver.is_alive():
                show(live, _status_line(run, runs, "fleet", time.monotonic() - fleet_t0,
                                        args.seconds, fleet, poller, started_wall))
                for name, proc in stack.procs.items():
                    if proc.poll() is not None:
                        fleet.stop()
                        raise RuntimeError(f"{name} exited ({proc.returncode}) during the run; "
                                           f"see {stack.log_dir}")
                driver.join(0.25)
            cpu_after = meter.snapshot()
            fleet_wall = time.monotonic() - fleet_t0
            result["rss_mb_after_fleet"] = resident_by_component(stack.procs)
            ended_wall = time.time()
            if fleet_error:
                raise fleet_error[0]
            published = list(fleet.stats.published)
            keys = {(k, r, ts): wall for k, r, ts, wall in published}
            n_poses = sum(1 for k in keys if k[0] == KEYS_PER_POSE)
            n_chunks = len(keys) - n_poses
            warm_poses = sum(1 for k in warm_keys if k[0] == KEYS_PER_POSE)
            expected = {"poses": n_poses + warm_poses,
                        "chunk_events": n_chunks + len(warm_keys) - warm_poses}
            # Drained when /api/v1/stats counts every published event (the store folds
            # duplicates, so reaching the count means each one is stored), then a moment
            # more for the poller to see the last ones. A backlog still being stored is
            # waited for (it is slow, not lost: the sustained rate pays for it); only
            # what is missing once the store stops counting is lost.
            drain_t0 = time.monotonic()
            drain = DrainWatch(expected)
            stats_client = httpx.Client(timeout=30)
            while not drain.given_up(time.monotonic() - drain_t0):
                show(live, _status_line(run, runs, "drain", time.monotonic() - drain_t0,
                                        DRAIN_MAX_S, fleet, poller, started_wall))
                if drain.drained_s is None:
                    try:
                        counts = stats_client.get(f"{stack.api_url}/api/v1/stats").json()
                        drain.observe(time.monotonic() - drain_t0, counts)
                    except (httpx.HTTPError, ValueError):
                        pass
                if drain.drained_s is not None and keys.keys() <= (poller.first_seen.keys() | poller.censored):
                    break
                time.sleep(0.25)
            drain_s = drain.drained_s
            drain_waited_s = time.monotonic() - drain_t0
            stats_client.close()
            acked = [after - before for before, after in
                     zip(acked_before, gateway_acks(stack.gateway_health_ports))]
            # Per run (each has a fresh server): gaps the guard read again, and gaps it
            # gave up on (records it never read: they show up as lost).
            metrics_after = server_metrics(stack.api_url)
            gaps = history_offset_gaps(metrics_after)
            stages = store_stages(stages_before, histogram_totals(metrics_after),
                                  time.monotonic() - stages_t0)
        console.print(_status_line(run, runs, "done", time.monotonic() - fleet_t0, args.seconds,
                                   fleet, poller, started_wall))
        poller.stop()
        poller.join()
        listener.stop()
        listener.join(5)
        all_seen = keys.keys() <= poller.first_seen.keys()

        with console.status(f"run {run}/{runs}: scanning the run window through the API..."):
            first_ts = min(ts for _, _, ts, _ in published)
            last_ts = max(ts for _, _, ts, _ in published)
            slice_ms = max(1000, int(50_000 / max(args.robots, 1)) * 1000)
            scanned = scan_run(stack.api_url, first_ts - 1000, last_ts + 1001, slice_ms)
            stats = httpx.get(f"{stack.api_url}/api/v1/stats", timeout=60).json()

        fleet_rows = [k for kind in scanned.values() for k in kind
                      if not k[1].startswith(WARMUP_PREFIX)]
        unique = set(fleet_rows)
        lost = [k for k in keys if k not in unique]
        unexpected = [k for k in unique if k not in keys]
        queryable_at = queryable_times(poller.first_seen, listener.pushed_at)
        upper, lower = _latencies(queryable_at, poller.not_seen_at, keys)
        polled, _ = _latencies(poller.first_seen, poller.not_seen_at, keys)
        pushed = [at - keys[k] for k, at in listener.pushed_at.items() if k in keys]
        # What the poll adds to the push: the push is sent once the insert returned, so an
        # event seen by a poll long after its push was queryable and waited for the poller.
        poll_after_push = [poller.first_seen[k] - at for k, at in listener.pushed_at.items()
                           if k in keys and k in poller.first_seen]
        pose_upper = [v for k, v in zip(keys, upper) if k[0] == KEYS_PER_POSE]
        chunk_upper = [v for k, v in zip(keys, upper) if k[0] == KEYS_PER_CHUNK]
        stored_events = len(unique & keys.keys())
        cpu_pct = CpuMeter.percent(cpu_before, cpu_after,
                                   fleet.stats.report.get("cpu_s") if loadgen == "raw" else None)
        aligned = getattr(args, "aligned_chunks", False)
        scheduled = (fleet.stats.report.get("scheduled_events") if loadgen == "raw"
                     else fleet.scheduled_events(int(args.seconds)))
        result.update({
            "robots": args.robots,
            "seconds": args.seconds,
            "fleet_wall_s": fleet_wall,
            "offered_events_per_s": args.robots * getattr(fleet, "events_per_robot_s", 1.2),
            "published_poses": n_poses,
            "published_chunks": n_chunks,
            "published_events": len(keys),
            "scheduled_events": scheduled,
            "loadgen": loadgen,
            # spread: robot i's chunk cycle offset by i poses; aligned: the whole fleet's
            # chunks in one second of five (robot/schedule.py)
            "chunk_schedule": "aligned" if aligned else "spread",
            "loadgen_schedule_percent": 100.0 * len(keys) / scheduled if scheduled else None,
            "loadgen_report": getattr(fleet.stats, "report", {}),
            "published_events_per_s": len(keys) / args.seconds,
            "published_duplicate_keys": len(published) - len(keys),
            "stored_events": stored_events,
            # Over the time from the first publish until the last event was stored: a
            # pipeline that needs a long drain after the fleet stops did not sustain the rate.
            "sustained_events_per_s": stored_events / (args.seconds + (
                drain_s if drain_s is not None else drain_waited_s)),
            "lost": len(lost),
            "lost_examples": [list(k) for k in lost[:10]],
            "duplicated": len(fleet_rows) - len(unique),
            "unexpected": len(unexpected),
            "stats_endpoint": stats,
            "stats_expected": expected,
            "stats_poses_minus_expected": stats["poses"] - expected["poses"],
            "stats_chunk_events_minus_expected": stats["chunk_events"] - expected["chunk_events"],
            "dead_letters": stats["dead_letters"],
            "all_seen_by_poller": all_seen,
            "drain_s": drain_s,
            "drain_waited_s": drain_waited_s,
            "drained": drain_s is not None,
            # What the gateways had Kafka confirm (and so acknowledged to the broker) during
            # the run, against what the robots had acknowledged: 0 if the broker passed on
            # every message. With events lost, it says on which side of the gateways.
            "gateway_acked_by_replica": acked,
            "gateway_acked_minus_published": sum(acked) - len(keys),
            "history_offset_gaps_reread": gaps["reread"],
            "history_offset_gaps_accepted": gaps["accepted"],
            # From the fleet's start to the drain: what each batch cost the store thread.
            "store_stages": stages,
            "latency_samples": len(upper),
            "latency_censored": sum(1 for v in upper if v == INF),
            "latency_p50_s": _pct(upper, 50),
            "latency_p90_s": _pct(upper, 90),
            "latency_p99_s": _pct(upper, 99),
            "latency_max_s": max(upper) if upper else None,
            "latency_polled_p50_s": _pct(polled, 50),
            "latency_polled_p99_s": _pct(polled, 99),
            "latency_pushed_p50_s": _pct(pushed, 50),
            "latency_pushed_p99_s": _pct(pushed, 99),
            "live_pushed_events": len(pushed),
            "live_errors": listener.errors,
            "live_last_error": listener.last_error,
            "latency_lower_bound_p50_s": _pct(lower, 50),
            "latency_lower_bound_p99_s": _pct(lower, 99),
            "pose_latency_p50_s": _pct(pose_upper, 50),
            "pose_latency_p99_s": _pct(pose_upper, 99),
            "chunk_latency_p50_s": _pct(chunk_upper, 50),
            "chunk_latency_p99_s": _pct(chunk_upper, 99),
            **_stage_latencies(poller.received_at, queryable_at, keys),
            "poller": {
                "interval_target_s": args.poll_interval,
                "polls": poller.polls,
                "poll_p50_s": _pct(poller.poll_seconds, 50),
                "poll_p99_s": _pct(poller.poll_seconds, 99),
                "cycle_p50_s": _pct(poller.cycle_seconds, 50),
                "cycle_p99_s": _pct(poller.cycle_seconds, 99),
                "cycle_max_s": max(poller.cycle_seconds, default=None),
                "seen_after_push_p50_s": _pct(poll_after_push, 50),
                "seen_after_push_p99_s": _pct(poll_after_push, 99),
                "rows_per_poll_p50": _pct(poller.window_rows, 50),
                "errors": poller.errors,
                "last_error": poller.last_error,
                "truncated_polls": poller.truncated_polls,
                "in_response_duplicates": poller.in_response_duplicates,
            },
            "cpu_percent_of_one_core": cpu_pct,
            "cpu_us_per_event": cpu_us_per_event(cpu_pct, len(keys), fleet_wall),
            "loadgen_nice": LOADGEN_NICE,
            "run_started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started_wall)),
            "run_ended_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ended_wall)),
            "loadavg_after_fleet": os.getloadavg(),
            "loadavg_1min_after_fleet": os.getloadavg()[0],
        })
    finally:
        gc.enable()
        if poller is not None:
            poller.stop()
        if listener is not None:
            listener.stop()
        stack.stop()

    with console.status(f"run {run}/{runs}: OPTIMIZE FINAL and measuring bytes on disk..."):
        storage = measure_storage(data_dir)
    total = sum(storage["table_bytes"].values())
    robot_days = args.robots * args.seconds / 86_400
    per_table = {t: b / robot_days for t, b in storage["table_bytes"].items()}
    events_only = sum(storage["table_bytes"].get(t, 0) for t in ("poses", "chunk_events"))
    result["storage"] = {
        **storage,
        "total_bytes": total,
        "robot_days": robot_days,
        "bytes_per_robot_day": total / robot_days,
        "bytes_per_robot_day_by_table": per_table,
        "bytes_per_robot_day_events_only": events_only / robot_days,
        "bytes_per_pose": storage["table_bytes"].get("poses", 0) / max(result["published_poses"], 1),
        "bytes_per_chunk_event": storage["table_bytes"].get("chunk_events", 0)
        / max(result["published_chunks"], 1),
    }
    result["bytes_per_robot_day"] = total / robot_days
    return result


# --- reporting ----------------------------------------------------------------------------


def _flatten(d: dict, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, name + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[name] = v
    return out


def medians(runs: list[dict]) -> dict[str, float]:
    flat = [_flatten(r) for r in runs]
    keys = set().union(*flat)
    return {k: statistics.median(f[k] for f in flat if k in f)
            for k in sorted(keys) if all(k in f for f in flat)}


def _mb(v: float) -> str:
    return f"{v / 1e6:,.2f} MB"


def _s(v: float | None) -> str:
    if v is None:
        return "n/a"
    return f"> {MAX_WINDOW_MS / 1000:.0f} s (censored)" if v == INF else f"{v:.3f} s"


def _json_safe(v):
    if isinstance(v, float) and v in (INF, -INF):
        return None  # JSON has no infinity: a censored latency (> 30 s) is written as null
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    return v


MIN_STORAGE_JUDGED_S = 120.0  # shorter runs: storage per robot-day is mostly fixed overhead


def storage_verdict(seconds: float, bytes_per_robot_day: float) -> bool | None:
    """Met / missed the per-robot-day storage target; None (not judged) on runs too short
    for it: their fixed overhead scaled up to a day says nothing about growth."""
    if seconds < MIN_STORAGE_JUDGED_S:
        return None
    return bytes_per_robot_day <= TARGETS["bytes_per_robot_day"]


def live_bounds(robots: int, med: dict) -> list[tuple[str, str, float | None, bool]]:
    """(what, target, measured, held) for each of issue 16's bounds, on a run's (or the
    runs' medians') figures."""
    offered = robots * 1.2
    get = lambda k: med.get(k)  # noqa: E731
    schedule = get("loadgen_schedule_percent")
    checks = [
        ("lost", "0", get("lost"), get("lost") == 0),
        ("duplicated", "0", get("duplicated"), get("duplicated") == 0),
        ("sustained (events/s)", f">= {SUSTAINED_MIN_FRACTION * offered:,.0f}",
         get("sustained_events_per_s"),
         (get("sustained_events_per_s") or 0) >= SUSTAINED_MIN_FRACTION * offered),
        ("load generator: acknowledged / scheduled (%)", f">= {SCHEDULE_MIN_PERCENT}", schedule,
         schedule is not None and schedule >= SCHEDULE_MIN_PERCENT),
        ("p99 by the live push", f"<= {PUSH_P99_MAX_S:g} s", get("latency_pushed_p99_s"),
         (get("latency_pushed_p99_s") or INF) <= PUSH_P99_MAX_S),
        ("p99 by the poll", f"<= {POLL_P99_MAX_S:g} s", get("latency_polled_p99_s"),
         (get("latency_polled_p99_s") or INF) <= POLL_P99_MAX_S),
    ]
    if robots <= SMALL_FLEET:
        checks.append(("p99 (push or poll)", f"<= {SMALL_FLEET_P99_S:g} s", get("latency_p99_s"),
                       (get("latency_p99_s") or INF) <= SMALL_FLEET_P99_S))
    return checks


def judged(seconds: float) -> bool:
    """Whether a run is long enough to be judged against the bounds."""
    return seconds >= MIN_JUDGED_S


def print_results(console, args, facts: dict, runs: list[dict], med: dict) -> None:
    from rich.table import Table

    n = len(runs)
    title = (f"mapservice bench ingest: {args.robots} robots, {args.seconds:.0f} s, "
             f"MQTT {args.mqtt}, {'median of ' + str(n) + ' runs' if n > 1 else '1 run'}")
    table = Table(title=title)
    table.add_column("measure")
    table.add_column("target", justify="right")
    table.add_column("measured", justify="right")
    table.add_column("", justify="center")

    judge = judged(args.seconds)

    def row(name, target, value, ok=None):
        # A run too short to be representative says so instead of a red MISSED.
        mark = ("" if ok is None else "[dim]not judged[/dim]" if not judge else
                "[green]ok[/green]" if ok else "[red]MISSED[/red]")
        table.add_row(name, target, value, mark)

    offered = med["offered_events_per_s"]
    bounds = {name: (target, ok) for name, target, _, ok in live_bounds(args.robots, med)}
    row("offered load (events/s)", "", f"{offered:,.0f}")
    row("published = acknowledged by the broker (events/s)", "", f"{med['published_events_per_s']:,.1f}")
    schedule = med.get("loadgen_schedule_percent")
    row("load generator: acknowledged / scheduled", *bounds["load generator: acknowledged / scheduled (%)"][:1],
        f"{schedule:.2f} %" if schedule is not None else "n/a",
        bounds["load generator: acknowledged / scheduled (%)"][1])
    if "loadgen_report.lag_p99_s" in med:
        row("  load generator: p99 lateness / write -> PUBACK p99", "",
            f"{_s(med.get('loadgen_report.lag_p99_s'))} / {_s(med.get('loadgen_report.puback_p99_s'))}")
    row("sustained = stored / (seconds + drain time)", bounds["sustained (events/s)"][0],
        f"{med['sustained_events_per_s']:,.1f}", bounds["sustained (events/s)"][1])
    row("lost", "0", f"{med['lost']:,.0f}", med["lost"] == 0)
    row("duplicated (rows beyond one per key)", "0", f"{med['duplicated']:,.0f}", med["duplicated"] == 0)
    row("stats poses - published", "0", f"{med['stats_poses_minus_expected']:,.0f}",
        med["stats_poses_minus_expected"] == 0)
    row("stats chunk events - published", "0", f"{med['stats_chunk_events_minus_expected']:,.0f}",
        med["stats_chunk_events_minus_expected"] == 0)
    row("dead letters", "0", f"{med['dead_letters']:,.0f}", med["dead_letters"] == 0)
    row("publish -> queryable p50 (push or poll)", "", _s(med.get("latency_p50_s")))
    small = bounds.get("p99 (push or poll)")
    row("publish -> queryable p99 (push or poll)", small[0] if small else "",
        _s(med.get("latency_p99_s")), small[1] if small else None)
    row("  p99 by the live push alone", bounds["p99 by the live push"][0],
        _s(med.get("latency_pushed_p99_s")), bounds["p99 by the live push"][1])
    row("  p99 by the poll alone", bounds["p99 by the poll"][0],
        _s(med.get("latency_polled_p99_s")), bounds["p99 by the poll"][1])
    row("  p50 by the push / by the poll", "",
        f"{_s(med.get('latency_pushed_p50_s'))} / {_s(med.get('latency_polled_p50_s'))}")
    row("  p50 / p99 lower bound (poll excluded)", "",
        f"{_s(med.get('latency_lower_bound_p50_s'))} / {_s(med.get('latency_lower_bound_p99_s'))}")
    row("  events pushed live / published", "",
        f"{med.get('live_pushed_events', 0):,.0f} / {med['published_events']:,.0f}")
    row("publish -> queryable max", "", _s(med.get("latency_max_s")))
    row("  publish -> gateway p50 / p99", "",
        f"{_s(med.get('publish_to_gateway_p50_s'))} / {_s(med.get('publish_to_gateway_p99_s'))}")
    row("  gateway -> queryable p50 / p99", "",
        f"{_s(med.get('gateway_to_queryable_p50_s'))} / {_s(med.get('gateway_to_queryable_p99_s'))}")
    row("history offset gaps read again / given up", "given up: 0",
        f"{med.get('history_offset_gaps_reread', 0):,.0f} / {med.get('history_offset_gaps_accepted', 0):,.0f}",
        med.get("history_offset_gaps_accepted", 0) == 0)
    row("events unseen within 30 s window", "0", f"{med['latency_censored']:,.0f}",
        med["latency_censored"] == 0)
    row("drain: fleet stop -> all stored", "", _s(med.get("drain_s")) if "drain_s" in med
        else "not drained")
    # Fixed overhead (the map's chunk contents, table parts, the schema) is scaled up to a
    # day with the run: on a short run it dominates and says nothing about per-robot growth.
    verdict = storage_verdict(args.seconds, med["bytes_per_robot_day"])
    row("stored bytes per robot-day (all tables)", _mb(TARGETS["bytes_per_robot_day"]),
        _mb(med["bytes_per_robot_day"]) + ("" if verdict is not None else
                                           f" (not judged: run < {MIN_STORAGE_JUDGED_S:.0f} s)"),
        verdict)
    for t in ("poses", "chunk_events", "chunk_contents", "pose_keyframes", "conflicts", "map_meta",
              "dead_letters", "schema_migrations"):
        k = f"storage.bytes_per_robot_day_by_table.{t}"
        if k in med:
            row(f"  of which {t}", "", _mb(med[k]))
    row("  events only (poses + chunk_events)", "", _mb(med["storage.bytes_per_robot_day_events_only"]))
    row("2019 (Elasticsearch, 20 robots)", "", _mb(BASELINE_2019["bytes_per_robot_day"]))
    for k in ("kafka", "mqtt", "gateway", "server", "stack_total", "loadgen", "latency_probes",
              "other_processes", "irq_softirq", "steal", "machine_busy_all_cores"):
        key = f"cpu_percent_of_one_core.{k}"
        if key in med:
            per_event = med.get(f"cpu_us_per_event.{k}")
            row(f"CPU {k} (% of one core" + (", µs per event)" if per_event is not None else ")"),
                "", f"{med[key]:.1f} %" + (f", {per_event:.0f} µs" if per_event is not None else ""))
    if "yardstick_ms" in med:
        row("machine yardstick before the run (ms, lower = faster machine)", "",
            f"{med['yardstick_ms']:.1f}")
    console.print(table)
    if not judge:
        console.print(f"[yellow]A {args.seconds:.0f} s run is not representative (start-up noise "
                      f"dominates): reported, not judged; judged runs last >= {MIN_JUDGED_S:.0f} s.[/yellow]")
    other = med.get("cpu_percent_of_one_core.other_processes", 0.0)
    console.print(f"load average at the end of the fleet: {med.get('loadavg_1min_after_fleet', float('nan')):.2f}; "
                  f"other processes took {other:.0f} % of a core"
                  + (" (a shared machine: development numbers)" if other > 15 else ""))
    console.print(f"machine: {facts['nproc']} CPUs ({facts['cpu_model']}), "
                  f"{facts['ram_bytes'] / 2**30:.1f} GiB RAM, Python {facts['python']}, "
                  f"Kafka: {facts.get('kafka', facts['tansu'])}, {facts['mosquitto']}")
    console.print("latency = the first moment the event was known queryable minus the load "
                  "generator's publish time: the server's send time of its push on the live "
                  "WebSocket (sent after its insert returned) or the end of the first poll of the API "
                  f"that returned it (every ~{args.poll_interval * 1000:.0f} ms, so up to one "
                  "poll interval plus the poll's own duration late), whichever came first; the "
                  "lower bound uses the start of the last poll that did not return it yet. "
                  "Sustained = events stored / (--seconds + drain time).")


def run_series(args, base: Path, console) -> tuple[list[dict], dict]:
    """`--repeat` runs of `args.robots` robots (fresh stack each, under `base`); their medians."""
    runs: list[dict] = []
    for i in range(1, args.repeat + 1):
        run_dir = base / f"run-{i}"
        if run_dir.exists():
            shutil.rmtree(run_dir)
        result = run_once(args, run_dir, i, args.repeat, console)
        runs.append(result)
        cpu = result["cpu_percent_of_one_core"]
        console.print(f"run {i} ({args.robots:,} robots): lost {result['lost']}, duplicated "
                      f"{result['duplicated']}, generator {result['loadgen_schedule_percent'] or 0:.2f} % "
                      f"of schedule, p99 push {_s(result['latency_pushed_p99_s'])} / poll "
                      f"{_s(result['latency_polled_p99_s'])}, sustained "
                      f"{result['sustained_events_per_s']:,.0f}/s, "
                      f"{_mb(result['bytes_per_robot_day'])}/robot-day, CPU {cpu['stack_total']:.0f} % "
                      f"stack + {cpu['loadgen']:.0f} % loadgen, load {result['loadavg_1min_after_fleet']:.2f}")
        if result["lost"]:
            console.print(f"[red]{loss_side(result['gateway_acked_minus_published'])}[/red]")
    return runs, medians(runs)


def loss_side(acked_minus_published: float) -> str:
    """Where lost events went missing, from what the gateways had Kafka confirm."""
    if acked_minus_published < 0:
        return (f"the gateways had {-acked_minus_published:.0f} fewer messages confirmed than the "
                "robots had acknowledged: the MQTT broker did not pass them on (or a gateway "
                "still holds them); see the broker's and the gateways' logs")
    return ("the gateways had every published message confirmed by Kafka: the events were lost "
            "after them (Kafka, the history consumer or the store); see the server's log")


def ceiling_verdict(steps: list[dict]) -> int | None:
    """The largest fleet of consecutive steps from the first that held every bound."""
    largest = None
    for step in steps:
        if not step["held"]:
            break
        largest = step["robots"]
    return largest


def find_ceiling(args, facts: dict, base: Path, console) -> dict:
    """Steps the fleet up until a step's medians miss a bound (or --ceiling-max)."""
    import argparse

    steps: list[dict] = []
    robots = args.robots
    while robots <= args.ceiling_max:
        step_args = argparse.Namespace(**{**vars(args), "robots": robots})
        runs, med = run_series(step_args, base / f"robots-{robots}", console)
        print_results(console, step_args, facts, runs, med)
        checks = live_bounds(robots, med)
        held = all(ok for *_, ok in checks)
        steps.append({"robots": robots, "held": held,
                      "missed": [name for name, _, _, ok in checks if not ok],
                      "medians": med, "runs": runs})
        console.print(f"{robots:,} robots: " + ("held every bound" if held else
                                                  "missed " + ", ".join(steps[-1]["missed"])))
        if not held:
            break
        robots += args.ceiling_step
    largest = ceiling_verdict(steps)
    console.print(f"[bold]largest fleet that held every bound: "
                  f"{f'{largest:,} robots' if largest else 'none of the steps'}[/bold]"
                  + ("" if judged(args.seconds) else f" (runs of {args.seconds:.0f} s: not "
                     "representative)"))
    return {"steps": steps, "largest_fleet_held": largest}


def main(args) -> None:
    from rich.console import Console

    from mapservice.runtime.logs import configure

    configure("WARNING", "console", "bench")
    console = Console()
    if not console.is_terminal:
        console = Console(width=120)  # a log file: keep the result table on one line a row
    if args.robots < 1 or args.seconds <= 0 or args.repeat < 1:
        sys.exit("--robots, --seconds and --repeat must be positive")
    facts = machine_facts()
    base = Path(args.data_dir) if args.data_dir else Path(tempfile.mkdtemp(prefix="mapservice-bench-"))
    base.mkdir(parents=True, exist_ok=True)
    doc = {
        "benchmark": "ingest",
        "command": "mapservice bench ingest " + " ".join(sys.argv[3:] if sys.argv[1:3] == ["bench", "ingest"] else sys.argv[1:]),
        "args": {"robots": args.robots, "seconds": args.seconds, "mqtt": args.mqtt,
                 "repeat": args.repeat, "data_dir": str(base),
                 "loadgen": getattr(args, "loadgen", "raw")},
        "machine": facts,
        "targets": TARGETS,
        "live_bounds": {"schedule_min_percent": SCHEDULE_MIN_PERCENT,
                        "sustained_min_fraction": SUSTAINED_MIN_FRACTION,
                        "push_p99_max_s": PUSH_P99_MAX_S, "poll_p99_max_s": POLL_P99_MAX_S,
                        "small_fleet": SMALL_FLEET, "small_fleet_p99_s": SMALL_FLEET_P99_S,
                        "min_judged_s": MIN_JUDGED_S},
        "baseline_2019": BASELINE_2019,
    }
    if getattr(args, "find_ceiling", False):
        doc["ceiling"] = find_ceiling(args, facts, base, console)
    else:
        runs, med = run_series(args, base, console)
        print_results(console, args, facts, runs, med)
        doc.update({"medians": med, "runs": runs,
                    "bounds_held": all(ok for *_, ok in live_bounds(args.robots, med))
                    if judged(args.seconds) else None})
    doc["machine"]["loadavg_at_end"] = os.getloadavg()
    if args.json:
        Path(args.json).write_text(json.dumps(_json_safe(doc), indent=2, default=str))
        console.print(f"results written to {args.json}")
