"""One run of the ingest benchmark: a fresh stack, a warm-up, the load fleet with the
latency probes and CPU meter running, the drain, the scan and the bytes on disk.
"""

from __future__ import annotations

import gc
import os
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from mapservice.bench.ingest.cpu import CpuMeter, cpu_us_per_event
from mapservice.bench.ingest.latency import INF, _latencies, _pct, _stage_latencies, queryable_times
from mapservice.bench.ingest.metrics import (
    RECEIVED_LATENCY,
    gateway_acks,
    histogram_buckets,
    histogram_totals,
    history_offset_gaps,
    server_metrics,
    store_stages,
    stored_latency,
)
from mapservice.bench.ingest.probes import (
    DRAIN_MAX_S,
    KEYS_PER_CHUNK,
    KEYS_PER_POSE,
    DrainWatch,
    Key,
    LiveListener,
    QueryablePoller,
)
from mapservice.bench.ingest.profile import start_profilers
from mapservice.bench.ingest.report import SMALL_FLEET_P99_S, latency_clients
from mapservice.bench.ingest.storage import measure_storage, scan_run, storage_figures
from mapservice.bench.procstat import resident_by_component
from mapservice.bench.yardstick import yardstick_ms

WARMUP_PREFIX = "warmup"


LOADGEN_NICE = 10  # added to the load generator's threads' niceness (Linux: per thread)


def _status_line(
    run: int,
    runs: int,
    phase: str,
    elapsed: float,
    seconds: float,
    fleet,
    poller: QueryablePoller | None,
    started_wall: float,
) -> str:
    from rich.markup import escape

    pub = fleet.stats.poses + fleet.stats.chunks
    span = max(time.time() - started_wall, 1e-6)
    line = (
        f"run {run}/{runs} {phase} {elapsed:5.1f}/{seconds:.0f} s | published {pub:,} "
        f"({fleet.stats.poses:,} poses, {fleet.stats.chunks:,} chunks, {pub / span:,.0f}/s)"
    )
    if poller is None:  # --no-latency-clients: nothing here sees what is queryable
        return escape(line)
    seen = len(poller.first_seen)
    poll = poller.poll_seconds[-1] * 1000 if poller.poll_seconds else 0.0
    return escape(
        f"{line} | queryable {seen:,} ({seen / span:,.0f}/s) | not yet {pub - seen:,} | "
        f"last poll {poll:.0f} ms"
    )


def run_once(args, data_dir: Path, run: int, runs: int, console) -> dict:
    from rich.live import Live

    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.local.stack import Stack
    from mapservice.robot import DEFAULT_MAP

    data_dir.mkdir(parents=True, exist_ok=True)
    ros_map = load_ros_map(DEFAULT_MAP)
    gateways = getattr(args, "gateways", 1)
    # `kafka`: "apache" or "tansu" (bench/compare.py runs both); unset: the setting's choice.
    # A compared variant's settings and Python (bench/compare.py), if any.
    stack = Stack(
        data_dir,
        mqtt=args.mqtt,
        gateways=gateways,
        kafka=getattr(args, "kafka", ""),
        extra_env=dict(getattr(args, "stack_env", None) or {}),
        python=getattr(args, "stack_python", None) or "",
    )
    result: dict = {"data_dir": str(data_dir), "gateways": gateways}
    poller: QueryablePoller | None = None
    listener: LiveListener | None = None
    try:
        # Before the stack starts: the machine's speed right now, to compare runs by.
        result["yardstick_ms"] = yardstick_ms()
        t_start = time.monotonic()
        with console.status(
            f"run {run}/{runs}: starting Kafka ({stack.kafka}), {args.mqtt}, server, "
            f"{gateways} gateway(s)..."
        ):
            stack.start_brokers()
            stack.publish_meta(meta_for(ros_map))
            stack.start_server()
            stack.start_gateways()
        result["stack_start_s"] = time.monotonic() - t_start

        # Warm-up: proves MQTT -> gateway -> Kafka -> processors -> ClickHouse -> API is live.
        with console.status(f"run {run}/{runs}: warm-up (waiting for the pipeline to consume)..."):
            warm_keys = warm_up(stack, ros_map)
        result["warmup_s"] = time.monotonic() - t_start - result["stack_start_s"]

        loadgen, fleet = _load_fleet(args, stack, ros_map, console, f"run {run}/{runs}")
        # The run's bookkeeping (a few hundred thousand keys and times, no cycles) made the
        # cyclic collector stop this process for 0.2-0.4 s every ~2 s late in a 5,000-robot
        # run, and the poller with it: the poll figure then measured those pauses.
        gc.disable()
        if latency_clients(args):
            poller = QueryablePoller(stack.api_url, fleet.stats.published, args.poll_interval)
            poller.start()
            poller._ready.wait(5)
            listener = LiveListener(stack.api_url)
            listener.start()
            listener.connected.wait(15)
        meter = CpuMeter(
            stack.procs,
            [poller.native_id, listener.native_id] if poller and listener else [],
            getattr(fleet, "pids", []),
        )
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
        metrics_before = server_metrics(stack.api_url)
        stages_before = histogram_totals(metrics_before)
        stored_before = histogram_buckets(metrics_before)
        received_before = histogram_buckets(metrics_before, RECEIVED_LATENCY)
        stages_t0 = time.monotonic()
        cpu_before = meter.snapshot()
        started_wall = time.time()
        fleet_t0 = time.monotonic()
        driver.start()
        profilers = start_profilers(args, stack, run)  # --profile: py-spy on each component
        last_line = [0.0]

        def show(live, line: str) -> None:
            live.update(line)
            if not console.is_terminal and time.monotonic() - last_line[0] >= 10:
                console.print(line)  # a log file gets a line every 10 s instead
                last_line[0] = time.monotonic()

        with Live(console=console, refresh_per_second=4, transient=True) as live:
            while driver.is_alive():
                show(
                    live,
                    _status_line(
                        run,
                        runs,
                        "fleet",
                        time.monotonic() - fleet_t0,
                        args.seconds,
                        fleet,
                        poller,
                        started_wall,
                    ),
                )
                for name, proc in stack.procs.items():
                    if proc.poll() is not None:
                        fleet.stop()
                        raise RuntimeError(
                            f"{name} exited ({proc.returncode}) during the run; see {stack.log_dir}"
                        )
                driver.join(0.25)
            cpu_after = meter.snapshot()
            fleet_wall = time.monotonic() - fleet_t0
            result["profiles"] = profilers.wait() if profilers else None  # files written
            result["rss_mb_after_fleet"] = resident_by_component(stack.procs)
            ended_wall = time.time()
            if fleet_error:
                raise fleet_error[0]
            published = list(fleet.stats.published)
            keys = {(k, r, ts): wall for k, r, ts, wall in published}
            n_poses = sum(1 for k in keys if k[0] == KEYS_PER_POSE)
            n_chunks = len(keys) - n_poses
            warm_poses = sum(1 for k in warm_keys if k[0] == KEYS_PER_POSE)
            expected = {
                "poses": n_poses + warm_poses,
                "chunk_events": n_chunks + len(warm_keys) - warm_poses,
            }
            # Drained when /api/v1/stats counts every published event (the store folds
            # duplicates, so reaching the count means each one is stored), then a moment
            # more for the poller to see the last ones. A backlog still being stored is
            # waited for (it is slow, not lost: the sustained rate pays for it); only
            # what is missing once the store stops counting is lost.
            drain_t0 = time.monotonic()
            drain = DrainWatch(expected)
            stats_client = httpx.Client(timeout=30)
            while not drain.given_up(time.monotonic() - drain_t0):
                show(
                    live,
                    _status_line(
                        run,
                        runs,
                        "drain",
                        time.monotonic() - drain_t0,
                        DRAIN_MAX_S,
                        fleet,
                        poller,
                        started_wall,
                    ),
                )
                if drain.drained_s is None:
                    try:
                        counts = stats_client.get(f"{stack.api_url}/api/v1/stats").json()
                        drain.observe(time.monotonic() - drain_t0, counts)
                    except (httpx.HTTPError, ValueError):
                        pass
                if drain.drained_s is not None and (
                    poller is None or keys.keys() <= (poller.first_seen.keys() | poller.censored)
                ):
                    break
                time.sleep(0.25)
            drain_s = drain.drained_s
            drain_waited_s = time.monotonic() - drain_t0
            stats_client.close()
            acked = [
                after - before
                for before, after in zip(acked_before, gateway_acks(stack.gateway_health_ports))
            ]
            # Per run (each has a fresh server): gaps the guard read again, and gaps it
            # gave up on (records it never read: they show up as lost).
            metrics_after = server_metrics(stack.api_url)
            gaps = history_offset_gaps(metrics_after)
            stages = store_stages(
                stages_before, histogram_totals(metrics_after), time.monotonic() - stages_t0
            )
            stored = stored_latency(
                stored_before, histogram_buckets(metrics_after), SMALL_FLEET_P99_S
            )
            received = stored_latency(
                received_before,
                histogram_buckets(metrics_after, RECEIVED_LATENCY),
                SMALL_FLEET_P99_S,
            )
        console.print(
            _status_line(
                run,
                runs,
                "done",
                time.monotonic() - fleet_t0,
                args.seconds,
                fleet,
                poller,
                started_wall,
            )
        )
        all_seen = None
        if poller is not None and listener is not None:
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

        fleet_rows = [
            k for kind in scanned.values() for k in kind if not k[1].startswith(WARMUP_PREFIX)
        ]
        unique = set(fleet_rows)
        lost = [k for k in keys if k not in unique]
        unexpected = [k for k in unique if k not in keys]
        stored_events = len(unique & keys.keys())
        cpu_pct = CpuMeter.percent(
            cpu_before, cpu_after, fleet.stats.report.get("cpu_s") if loadgen == "raw" else None
        )
        aligned = getattr(args, "aligned_chunks", False)
        scheduled = (
            fleet.stats.report.get("scheduled_events")
            if loadgen == "raw"
            else fleet.scheduled_events(int(args.seconds))
        )
        result.update(
            {
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
                "sustained_events_per_s": stored_events
                / (args.seconds + (drain_s if drain_s is not None else drain_waited_s)),
                "lost": len(lost),
                "lost_examples": [list(k) for k in lost[:10]],
                "duplicated": len(fleet_rows) - len(unique),
                "unexpected": len(unexpected),
                "stats_endpoint": stats,
                "stats_expected": expected,
                "stats_poses_minus_expected": stats["poses"] - expected["poses"],
                "stats_chunk_events_minus_expected": stats["chunk_events"]
                - expected["chunk_events"],
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
                "stored_events_timed": stored["events"],
                "stored_latency_p50_s": stored["p50_s"],
                "stored_latency_p99_s": stored["p99_s"],
                "stored_within_small_fleet_bound": stored["within_bound_fraction"],
                "received_to_stored_p50_s": received["p50_s"],
                "received_to_stored_p99_s": received["p99_s"],
                "latency_clients": poller is not None,
                **(
                    _latency_figures(args, keys, poller, listener)
                    if poller is not None and listener is not None
                    else {}
                ),
                "cpu_percent_of_one_core": cpu_pct,
                "cpu_us_per_event": cpu_us_per_event(cpu_pct, len(keys), fleet_wall),
                "loadgen_nice": LOADGEN_NICE,
                "run_started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started_wall)),
                "run_ended_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ended_wall)),
                "loadavg_after_fleet": os.getloadavg(),
                "loadavg_1min_after_fleet": os.getloadavg()[0],
            }
        )
    finally:
        gc.enable()
        if poller is not None:
            poller.stop()
        if listener is not None:
            listener.stop()
        stack.stop()

    with console.status(f"run {run}/{runs}: OPTIMIZE FINAL and measuring bytes on disk..."):
        storage = measure_storage(data_dir)
    result["storage"] = storage_figures(storage, args.robots, args.seconds, result)
    result["bytes_per_robot_day"] = result["storage"]["bytes_per_robot_day"]
    return result


def warm_up(stack, ros_map) -> set[Key]:
    """One extra robot publishes for a few seconds; returns its events once all are queryable
    (the pipeline MQTT -> gateway -> Kafka -> processors -> ClickHouse -> API is live)."""
    from mapservice.robot.loadgen import RobotFleet

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
    return warm_keys


def _load_fleet(args, stack, ros_map, console, label: str) -> tuple[str, Any]:
    """(its name, the fleet) for `--workload` and `--loadgen`: VdaFleet, RawFleet (its
    workers started) or RobotFleet; each has stats, run() and stop()."""
    from mapservice.robot.loadgen import RobotFleet

    loadgen = getattr(args, "loadgen", "raw")
    if getattr(args, "workload", "2019") == "vda5050":  # VDA 5050 vehicles (vda_fleet.py)
        from mapservice.bench.vda_fleet import VdaFleet

        return "vda5050", VdaFleet(stack.mqtt_url, ros_map, args.robots)
    if loadgen == "raw":
        from mapservice.bench.fleet.rawfleet import RawFleet

        # Worker processes at a lower priority: they stand for robots on other machines.
        fleet = RawFleet(
            stack.mqtt_url,
            ros_map,
            args.robots,
            processes=getattr(args, "loadgen_processes", None),
            nice=LOADGEN_NICE,
            aligned_chunks=getattr(args, "aligned_chunks", False),
        )
        with console.status(f"{label}: starting the load fleet's workers..."):
            fleet.start(args.seconds)
        return loadgen, fleet
    return loadgen, RobotFleet(
        stack.mqtt_url,
        ros_map,
        args.robots,
        record=True,
        aligned_chunks=getattr(args, "aligned_chunks", False),
    )


def _latency_figures(
    args, keys: dict[Key, float], poller: QueryablePoller, listener: LiveListener
) -> dict:
    """Publish -> queryable of the run's events (push or poll, each alone, per kind, the
    lower bound, the split at the gateway) and how the poller itself kept up."""
    queryable_at = queryable_times(poller.first_seen, listener.pushed_at)
    upper, lower = _latencies(queryable_at, poller.not_seen_at, keys)
    polled, _ = _latencies(poller.first_seen, poller.not_seen_at, keys)
    pushed = [at - keys[k] for k, at in listener.pushed_at.items() if k in keys]
    # What the poll adds to the push: the push is sent once the insert returned, so an
    # event seen by a poll long after its push was queryable and waited for the poller.
    poll_after_push = [
        poller.first_seen[k] - at
        for k, at in listener.pushed_at.items()
        if k in keys and k in poller.first_seen
    ]
    pose_upper = [v for k, v in zip(keys, upper) if k[0] == KEYS_PER_POSE]
    chunk_upper = [v for k, v in zip(keys, upper) if k[0] == KEYS_PER_CHUNK]
    return {
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
    }
