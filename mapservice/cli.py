"""`mapservice`: run the whole service, one component, simulated robots or a benchmark."""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path

from mapservice.local.up import cmd_up
from mapservice.robot import DEFAULT_MAP
from mapservice.runtime.heap import freeze_startup_heap
from mapservice.runtime.startup import settings_for
from mapservice.settings import Settings


def cmd_gateway(args) -> None:
    from mapservice.adapters.kafka_topics import ensure_topics
    from mapservice.ingest.gateway import run_gateway

    settings = settings_for("gateway")
    ensure_topics(settings)
    freeze_startup_heap()
    run_gateway(settings, args.health_port)


def cmd_serve(args, processors: bool = True, api: bool = True, component: str = "server") -> None:
    from mapservice.server import serve

    settings = settings_for(component)
    asyncio.run(
        serve(
            settings, processors=processors, api=api, health_port=getattr(args, "health_port", None)
        )
    )


def cmd_migrate(args) -> None:
    from mapservice.adapters.clickhouse.connection import ClickHouseConnection
    from mapservice.adapters.clickhouse.migrations import (
        ClickHouseSchema,
        MigrationChanged,
        MigrationLocked,
    )
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION

    settings = settings_for("migrate")
    connection = ClickHouseConnection.from_settings(settings)
    schema = ClickHouseSchema(connection)
    log = logging.getLogger("mapservice.migrate")
    try:
        if args.break_lock:
            log.info(
                "migration lock %s", "dropped" if schema.break_migration_lock() else "was not held"
            )
        before = schema.schema_version()
        version = schema.migrate(lock_timeout_s=args.lock_timeout_s)
    except (MigrationLocked, MigrationChanged) as exc:
        sys.exit(f"mapservice migrate: {exc}")
    finally:
        connection.close()
    log.info(
        "schema of %s at version %d (was %d; this release: %d)",
        settings.clickhouse_database,
        version,
        before,
        SCHEMA_VERSION,
    )


def cmd_clickhouse_server(args) -> None:
    import uvicorn

    from mapservice.runtime.thread_priority import keep_merges_low
    from mapservice.sql.apps import server_app

    settings = settings_for("clickhouse-server")
    app = server_app(settings, read_write=args.read_write)
    keep_merges_low(settings)  # this process holds the chDB directory: its merges run here
    log = logging.getLogger("mapservice.clickhouse-server")
    log.info(
        "ClickHouse HTTP interface over %s on http://%s:%d (%s)",
        app.state.chdb_path,
        args.host,
        args.port,
        "read-write" if args.read_write else "read-only",
    )
    uvicorn.run(
        app, host=args.host, port=args.port, log_config=None, log_level=None, access_log=False
    )


def cmd_sql(args) -> None:
    import httpx

    from mapservice.sql.credentials import analyst_password

    settings = Settings(data_dir=Path(args.data_dir)) if args.data_dir else Settings()
    password = args.password or analyst_password(settings)
    if not password:
        sys.exit(
            "mapservice sql: no analyst password: pass --password or set "
            "MAPSERVICE_ANALYST_PASSWORD"
        )
    query = args.query if args.query != "-" else sys.stdin.read()
    try:
        with httpx.stream(
            "POST",
            args.url.rstrip("/") + "/",
            content=query.encode(),
            params={"default_format": args.format},
            auth=(args.user or settings.analyst_username, password),
            timeout=settings.analyst_max_execution_s + 30,
        ) as reply:
            if reply.status_code != 200:
                sys.exit(reply.read().decode(errors="replace").strip())
            for chunk in reply.iter_bytes():
                sys.stdout.buffer.write(chunk)
    except httpx.HTTPError as exc:
        sys.exit(
            f"mapservice sql: cannot reach {args.url} ({exc}); is the service running "
            "(`make up`)? --url points elsewhere"
        )


def cmd_export(args) -> None:
    import httpx

    if args.dataset == "replay":
        url, params, ext = f"{args.api.rstrip('/')}/api/v1/exports/replay.mcap", {}, "mcap"
    else:
        url = f"{args.api.rstrip('/')}/api/v1/exports/tables/{args.dataset}"
        params, ext = {"format": args.format}, args.format
        if args.robot:
            params["robotId"] = args.robot
    params.update({"from": args.from_, "to": args.to})
    out = Path(args.out or f"{args.dataset}.{ext}")
    from mapservice.robot.api_client import writer_token

    # Exports are reads: open by default; where reads need a token, the robot-side one
    # (MAPSERVICE_API_TOKEN, or the one `up` generated) is sent.
    token = writer_token()
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        with httpx.stream("GET", url, params=params, timeout=600, headers=headers) as reply:
            if reply.status_code != 200:
                sys.exit(
                    f"mapservice export: {reply.status_code} {reply.read().decode(errors='replace')}"
                )
            with out.open("wb") as file:
                for chunk in reply.iter_bytes():
                    file.write(chunk)
    except httpx.HTTPError as exc:
        sys.exit(
            f"mapservice export: cannot reach {args.api} ({exc}); is the service running "
            "(`make up`)? --api points elsewhere"
        )
    print(f"wrote {out} ({out.stat().st_size:,} bytes)")


def cmd_demo_history(args) -> None:
    """Days of the shift simulator, fast-forwarded into a data dir nothing else has open."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.local.up_output import PROGRESS_LOG_S, ProgressLog
    from mapservice.runtime.logs import configure

    console = Console()
    # On a terminal a progress bar; else (a file, a pipe: the bar prints nothing there) a
    # log line every PROGRESS_LOG_S, so a logged first run shows it is getting on.
    configure("WARNING" if console.is_terminal else "INFO", "console", "demo-history")
    # The week's batches hold hundreds of thousands of objects at once: with Python's
    # default thresholds the collector walked them again and again, a tenth of the CPU.
    freeze_startup_heap()
    data_dir, days, robots = Path(args.data_dir), args.days, args.robots
    try:
        ros_map = load_ros_map(args.map)
    except (OSError, ValueError) as exc:
        sys.exit(f"mapservice demo-history: cannot read the map {args.map}: {exc}")
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.adapters.clock import SystemClock
    from mapservice.local.demo_history import backfill
    from mapservice.processors.incident_watch import thresholds_of

    settings = Settings(data_dir=data_dir)
    store = ClickHouseStore.from_settings(settings)
    try:
        store.migrate()
        if store.counts().poses:
            sys.exit(
                f"mapservice demo-history: {data_dir} already has history; it writes only "
                "into a fresh data dir"
            )
        what = f"simulating the last {days:g} days of {robots} robots"
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f} %"),
            TimeElapsedColumn(),
            console=console,
            transient=True,
            disable=not console.is_terminal,
        ) as bar:
            task = bar.add_task(what, total=1.0)
            logged = ProgressLog(what, PROGRESS_LOG_S)

            def progress(done: float) -> None:
                bar.update(task, completed=done)
                if not console.is_terminal:
                    logged.update(done)

            result = backfill(
                store,
                ros_map,
                days=days,
                robots=robots,
                now_ms=SystemClock().now_ms(),
                conflict_window_ms=int(settings.conflict_window_s * 1000),
                progress=progress,
                thresholds=thresholds_of(settings),
            )
    finally:
        store.close()
    console.print(
        f"wrote {days:g} days of demo history in {result.seconds:.0f} s: {result.poses:,} poses, "
        f"{result.chunk_writes:,} map changes, {result.conflicts} conflicts, "
        f"{result.incidents:,} incidents"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapservice", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    up = sub.add_parser("up", help="run everything on embedded defaults, with simulated robots")
    up.add_argument(
        "--data-dir",
        default=".mapservice-data",
        help="where ClickHouse data, broker data and logs live (resumed if present)",
    )
    up.add_argument("--robots", type=int, default=5, help="simulated robots (0: none)")
    up.add_argument("--map", default=str(DEFAULT_MAP), help="ROS map YAML for the simulation")
    up.add_argument(
        "--history-days",
        type=float,
        default=7.0,
        help="on a fresh data dir, first write this many days of simulated history "
        "(the shift simulator, fast-forwarded; about 11 s a day here); 0: none",
    )
    up.add_argument(
        "--load-test",
        action="store_true",
        help="simulate the 2019 load test (circles, re-sent chunks) instead of a shift",
    )
    up.add_argument(
        "--mqtt-url",
        help="use this MQTT broker instead of the embedded one "
        "(Mosquitto when installed, else amqtt)",
    )
    up.add_argument(
        "--auth",
        action="store_true",
        help="authentication on, as in production: the embedded broker is Mosquitto "
        "with a password file and ACL, each simulated robot gets its own MQTT "
        "credential (DATA_DIR/secrets/robots.json), anonymous MQTT clients are "
        "refused (REST writes always need a token)",
    )
    up.add_argument("--api-port", type=int, default=8080, help="HTTP API and replay UI port")
    up.add_argument(
        "--foxglove-port",
        type=int,
        default=8765,
        help="Foxglove WebSocket server port (Foxglove and Lichtblick connect to it)",
    )
    up.add_argument("--mqtt-port", type=int, default=1883, help="MQTT port for robots")
    up.add_argument("--kafka-port", type=int, default=0, help="0: a free port")
    up.add_argument(
        "--restart-base-s",
        type=float,
        default=1.0,
        metavar="SECONDS",
        help="first wait before restarting a component that exited; doubles on "
        "each failure in a row, at most 60 s",
    )
    up.add_argument(
        "--open-browser", action="store_true", help="open the replay UI in a browser once up"
    )
    up.set_defaults(func=cmd_up)

    gw = sub.add_parser("gateway", help="MQTT-to-Kafka gateway (configured from MAPSERVICE_*)")
    gw.add_argument(
        "--health-port",
        type=int,
        default=None,
        help="serve /healthz, /readyz and /metrics on this port (default: none)",
    )
    gw.set_defaults(func=cmd_gateway)

    pr = sub.add_parser(
        "processors", help="stream processors: history sink (needs a ClickHouse server)"
    )
    pr.add_argument(
        "--health-port",
        type=int,
        default=None,
        help="serve /healthz, /readyz and /metrics on this port (default: none)",
    )
    pr.set_defaults(func=lambda a: cmd_serve(a, api=False, component="processors"))

    api = sub.add_parser("api", help="HTTP API only (needs a ClickHouse server)")
    api.set_defaults(func=lambda a: cmd_serve(a, processors=False, component="api"))

    demo = sub.add_parser(
        "demo-history",
        help="write days of simulated shift history into a data "
        "dir (what `up` does on a fresh one)",
    )
    demo.add_argument(
        "--data-dir", default=".mapservice-data", help="the embedded data dir (not in use)"
    )
    demo.add_argument("--days", type=float, default=7.0, help="how many days back from now")
    demo.add_argument("--robots", type=int, default=5, help="simulated robots (ids sim-000, ...)")
    demo.add_argument("--map", default=str(DEFAULT_MAP), help="ROS map YAML of the floor")
    demo.set_defaults(func=cmd_demo_history)

    mig = sub.add_parser(
        "migrate",
        help="apply the ClickHouse schema migrations of this release "
        "once (production runs it as a Job; components then find the schema)",
    )
    mig.add_argument(
        "--lock-timeout-s",
        type=float,
        default=600.0,
        help="how long to wait for another running migration before giving up",
    )
    mig.add_argument(
        "--break-lock",
        action="store_true",
        help="first drop a lock left by a migration that died (check none runs!)",
    )
    mig.set_defaults(func=cmd_migrate)

    chs = sub.add_parser(
        "clickhouse-server",
        help="the ClickHouse HTTP interface over the data "
        "dir's chDB, for processes that run apart (the split deployment on one "
        "machine); the one process that opens the directory",
    )
    chs.add_argument("--host", default="127.0.0.1", help="address to listen on")
    chs.add_argument("--port", type=int, default=8123, help="port to listen on")
    chs.add_argument(
        "--read-write",
        action="store_true",
        help="let MAPSERVICE_CLICKHOUSE_USERNAME write (default: every user read-only)",
    )
    chs.set_defaults(func=cmd_clickhouse_server)

    sql = sub.add_parser(
        "sql",
        help="run one read-only SQL statement on the running service "
        "(the analyst's ClickHouse HTTP endpoint) and print the result",
    )
    sql.add_argument("query", help="the statement; - reads it from stdin")
    sql.add_argument(
        "--url",
        default="http://127.0.0.1:8080/clickhouse",
        help="the service's ClickHouse endpoint (the API's /clickhouse)",
    )
    sql.add_argument(
        "--format",
        default="PrettyCompact",
        help="a ClickHouse output format: PrettyCompact, CSVWithNames, JSONEachRow, "
        "Parquet, ... (a FORMAT clause in the query wins)",
    )
    sql.add_argument("--user", default=None, help="default: MAPSERVICE_ANALYST_USERNAME (analyst)")
    sql.add_argument(
        "--password",
        default=None,
        help="default: MAPSERVICE_ANALYST_PASSWORD, else the one `up` generated in the data dir",
    )
    sql.add_argument(
        "--data-dir",
        default=None,
        help="where to find the generated password (default: MAPSERVICE_DATA_DIR)",
    )
    sql.set_defaults(func=cmd_sql)

    export = sub.add_parser(
        "export",
        help="download a time window from the running service: "
        "the map and robots as MCAP (Foxglove, Lichtblick) or a table as "
        "CSV/Parquet",
    )
    export.add_argument(
        "dataset",
        choices=[
            "replay",
            "robot-poses",
            "chunk-changes",
            "chunk-conflicts",
            "dead-letters",
            "vehicle-states",
            "vehicle-errors",
            "vehicle-connections",
            "annotation-edits",
            "commands",
        ],
        help="replay: MCAP of map and robots (at most 24 h); else an analysts' "
        "view (docs/analysts.md; at most 7 days); vehicle-*: the VDA 5050 "
        "tables vda_states, vda_errors, vda_connections; annotation-edits, "
        "commands: the operators' annotation and command events",
    )
    export.add_argument(
        "--from",
        dest="from_",
        required=True,
        help="start, ISO 8601 (2026-11-23T08:00:00Z) or epoch ms",
    )
    export.add_argument("--to", required=True, help="end (exclusive), ISO 8601 or epoch ms")
    export.add_argument(
        "--format",
        choices=["csv", "parquet"],
        default="csv",
        help="for tables (replay is always MCAP)",
    )
    export.add_argument("--robot", default=None, help="only this robot (tables)")
    export.add_argument("--out", default=None, help="file to write (default: <dataset>.<ext>)")
    export.add_argument("--api", default="http://127.0.0.1:8080", help="the service's API")
    export.set_defaults(func=cmd_export)

    serve = sub.add_parser("serve", help="processors and API in one process (chdb needs this)")
    serve.set_defaults(func=cmd_serve)

    from mapservice.robot.cli import add_parsers as add_robot_parsers

    add_robot_parsers(sub)  # map, sim, robot, drive

    from mapservice.bench.cli import add_bench_parser

    add_bench_parser(sub)

    from mapservice.bench.load_history_cli import add_parser as add_load_history_parser

    add_load_history_parser(sub)

    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
