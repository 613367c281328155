"""`mapservice sim`: simulated robots on a real map, or the 2019 load test, over MQTT."""

from __future__ import annotations

import math
import signal
import sys
import time
from collections.abc import Callable
from typing import Protocol, TypeVar


class _Fleet(Protocol):
    def stop(self) -> None: ...


F = TypeVar("F", bound=_Fleet)
PROGRESS_EVERY_S = 10.0  # how often a run without a terminal logs its progress


def cmd_sim(args) -> None:
    import structlog

    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.runtime.startup import settings_for

    from .connection import robot_mqtt_from_args

    settings = settings_for("sim")
    log = structlog.get_logger("sim")
    mqtt_url = args.mqtt_url or settings.mqtt_url
    ros_map = load_ros_map(args.map)
    try:
        conn = robot_mqtt_from_args(args, mqtt_url, settings.mqtt_ca_file)
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    if args.load_test:
        return _load_test(args, mqtt_url, ros_map, log, conn)
    from rich.console import Console
    from rich.live import Live

    from mapservice.core.areas import AreaGrid
    from mapservice.processors.incident_watch import thresholds_of

    from .api_client import writer_token
    from .faults import Faults
    from .sim import SimConfig
    from .sim_incidents import for_incidents
    from .simrun import SimRunner, progress_table
    from .zone_feed import ZoneFeed

    # The operators' zones: read from the API (`up` names its own in the environment).
    feed = (
        None
        if args.no_zones
        else ZoneFeed(args.api or settings.public_base_url, writer_token(args.token))
    )

    config = SimConfig(change_every_s=args.change_every)
    if not args.no_incidents:
        # Sized against the processors' own thresholds, so each one is an incident.
        config = for_incidents(config, thresholds_of(settings))

    def make_runner() -> SimRunner:
        return SimRunner(
            mqtt_url,
            ros_map,
            args.robots,
            seed=args.seed,
            prefix=args.prefix,
            faults=Faults(args.clock_skew, args.loss, args.bad_rate),
            config=config,
            mqtt_conn=conn,
            zone_feed=feed,
            zone_topic=settings.zone_advertisement_topic,
            advertisement_topic=None if args.no_advertisements else settings.advertisement_topic,
            area_grid=AreaGrid(settings.advertisement_area_chunks),
            area_margin_m=args.area_margin,
        )

    console = Console()
    due = _every(PROGRESS_EVERY_S)

    def log_progress(r) -> None:
        if due():
            log.info("simulating", **_sim_stats(r.stats), rate_per_s=round(r.stats.rate(), 1))

    def run(runner: SimRunner) -> None:
        log.info("simulated robots starting", robots=args.robots, map=str(args.map), mqtt=mqtt_url)
        if console.is_terminal and not args.quiet:
            with Live(progress_table(runner), console=console, refresh_per_second=2) as live:
                runner.run(args.seconds, on_tick=lambda r: live.update(progress_table(r)))
        else:
            runner.run(args.seconds, on_tick=log_progress)

    runner = _run_fleet(make_runner, run, mqtt_url)
    log.info("simulation stopped", **_sim_stats(runner.stats))


def _load_test(args, mqtt_url, ros_map, log, conn) -> None:
    """The 2019 load test: one pose a second, the same chunks re-sent at new positions."""
    from mapservice.robot.loadgen import RobotFleet

    started, due = time.monotonic(), _every(PROGRESS_EVERY_S)

    def progress(stats) -> None:
        if due():
            elapsed = max(time.monotonic() - started, 1e-9)
            log.info(
                "simulating (load test)",
                robots=args.robots,
                poses=stats.poses,
                chunks=stats.chunks,
                rate_per_s=round((stats.poses + stats.chunks) / elapsed, 1),
            )

    _run_fleet(
        lambda: RobotFleet(mqtt_url, ros_map, args.robots, prefix=args.prefix, mqtt_conn=conn),
        lambda fleet: fleet.run(args.seconds, on_tick=progress),
        mqtt_url,
    )


def _run_fleet(make: Callable[[], F], run: Callable[[F], object], mqtt_url: str) -> F:
    """Makes a fleet (simulated robots or the load test's), lets SIGTERM stop it, and runs
    it until done or stopped; returns it for its final stats. What differs is `make` and
    `run`; a fleet that cannot be made (a bad argument) ends the command with why."""
    try:
        fleet = make()
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    signal.signal(signal.SIGTERM, lambda *_: fleet.stop())
    _until_stopped(lambda: run(fleet), fleet.stop, mqtt_url)
    return fleet


def _every(seconds: float) -> Callable[[], bool]:
    """True at most once every `seconds` (the first call included): the progress logs."""
    last = [-math.inf]

    def due() -> bool:
        now = time.monotonic()
        if now - last[0] < seconds:
            return False
        last[0] = now
        return True

    return due


def _sim_stats(s) -> dict:
    """The simulation's counters, as its progress and its final log lines name them."""
    return {
        "robots": s.robots,
        "poses": s.poses,
        "chunks": s.chunks,
        "bad": s.bad,
        "lost": s.lost,
        "errors": s.errors,
        "map_changes": s.map_changes,
        "advertisements_read": s.advertisements,
    }


def _until_stopped(run, stop, mqtt_url: str) -> None:
    """Runs the robots until done or Ctrl-C; an unreachable broker ends with what to do."""
    try:
        run()
    except KeyboardInterrupt:
        stop()
    except PermissionError as exc:
        sys.exit(
            f"{exc}; check the credentials file (`mapservice robot add <robotId> --save FILE`)"
        )
    except OSError as exc:
        sys.exit(
            f"cannot reach the MQTT broker at {mqtt_url}: {exc}; "
            "start one (e.g. `make up`) or pass --mqtt-url"
        )
