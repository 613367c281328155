"""`mapservice sim`: simulated robots on a real map, or the 2019 load test, over MQTT."""

from __future__ import annotations

import signal
import sys
import time


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

    from .api_client import writer_token
    from .faults import Faults
    from .sim import SimConfig
    from .simrun import SimRunner, progress_table
    from .zone_feed import ZoneFeed

    # The operators' zones: read from the API (`up` names its own in the environment).
    feed = (
        None
        if args.no_zones
        else ZoneFeed(args.api or settings.public_base_url, writer_token(args.token))
    )
    try:
        runner = SimRunner(
            mqtt_url,
            ros_map,
            args.robots,
            seed=args.seed,
            prefix=args.prefix,
            faults=Faults(args.clock_skew, args.loss, args.bad_rate),
            config=SimConfig(change_every_s=args.change_every),
            mqtt_conn=conn,
            zone_feed=feed,
            zone_topic=settings.zone_advertisement_topic,
        )
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    signal.signal(signal.SIGTERM, lambda *_: runner.stop())
    console = Console()
    log.info("simulated robots starting", robots=args.robots, map=str(args.map), mqtt=mqtt_url)
    last = [0.0]

    def log_progress(r) -> None:
        now = time.monotonic()
        if now - last[0] >= 10:
            last[0] = now
            s = r.stats
            log.info(
                "simulating",
                robots=s.robots,
                poses=s.poses,
                chunks=s.chunks,
                bad=s.bad,
                lost=s.lost,
                errors=s.errors,
                map_changes=s.map_changes,
                rate_per_s=round(s.rate(), 1),
            )

    def run() -> None:
        if console.is_terminal and not args.quiet:
            with Live(progress_table(runner), console=console, refresh_per_second=2) as live:
                runner.run(args.seconds, on_tick=lambda r: live.update(progress_table(r)))
        else:
            runner.run(args.seconds, on_tick=log_progress)

    _until_stopped(run, runner.stop, mqtt_url)
    s = runner.stats
    log.info(
        "simulation stopped",
        robots=s.robots,
        poses=s.poses,
        chunks=s.chunks,
        bad=s.bad,
        lost=s.lost,
        errors=s.errors,
        map_changes=s.map_changes,
    )


def _load_test(args, mqtt_url, ros_map, log, conn) -> None:
    """The 2019 load test: one pose a second, the same chunks re-sent at new positions."""
    from mapservice.robot.loadgen import RobotFleet

    try:
        fleet = RobotFleet(mqtt_url, ros_map, args.robots, prefix=args.prefix, mqtt_conn=conn)
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    signal.signal(signal.SIGTERM, lambda *_: fleet.stop())
    started, last = time.monotonic(), [0.0]

    def progress(stats) -> None:
        now = time.monotonic()
        if now - last[0] >= 10:
            last[0] = now
            log.info(
                "simulating (load test)",
                robots=args.robots,
                poses=stats.poses,
                chunks=stats.chunks,
                rate_per_s=round((stats.poses + stats.chunks) / max(now - started, 1e-9), 1),
            )

    _until_stopped(lambda: fleet.run(args.seconds, on_tick=progress), fleet.stop, mqtt_url)


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
